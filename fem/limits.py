"""What a description may ask for: sizes checked before anything is allocated, and ranges
of physical numbers inside which the arithmetic stays finite.

A size (tets, bodies, bytes of a file, legs of a dome) over its limit is a
`SizeLimitError`, which `lifted()` (the command line's --allow-large) switches off:
such a description is more likely a slip than a wish, and would take the machine's
whole memory before failing. The tet limit follows the machine: as many tets as
MEMORY_SHARE of the backend's memory holds (the GPU's on CUDA, else the host's), at
BYTES_PER_TET each; its message names the tets and the memory, asked and available.
A number outside its range (E = 1e308, dt = 1e-300, a body placed 1e308 m away) is a
plain FemError: no real scene needs it, and the squares and products of the step
would overflow.
"""

import contextlib
import ctypes
import ctypes.util
import functools
import os

from fem import runtime
from fem.errors import FemError, SizeLimitError

# Sizes, each lifted by lifted().
MAX_BODIES = 256             # the coarse preconditioner grows with the square of the body count
# Bytes the engine keeps per tet (the mesh, the solver's fields, per-vertex ones shared out):
# the process's memory over box meshes of 10k to 197k tets after two steps grows by 505 B/tet
# in f32 and 768 in f64 (CPU, Taichi 1.7.4); a tenth more for what building a scene holds.
BYTES_PER_TET = {"f32": 550, "f64": 850}
MEMORY_SHARE = 0.5           # of the backend's memory, for the tets of one scene: the rest is the machine's
MAX_FILE_BYTES = 256 * 2**20  # a mesh file; a million-tet MEDIT file is about 60 MB
# A scene file, TOML or coursework: the TOML parser takes about 25 times a file's size in memory
# (a 240 MB file: 6 GB, then MemoryError), a coursework file split into words about 15 times, and a
# scene names its meshes' files rather than holding them.
MAX_SCENE_FILE_BYTES = 16 * 2**20
MAX_DOME_LEGS = 64
_lifted = False

# Ranges of physical numbers (SI units); not lifted.
MAX_YOUNG_MODULUS = 1e13     # Pa; diamond is 1.2e12
MAX_DENSITY = 1e6            # kg/m^3; osmium is 2.3e4
DT_RANGE = (1e-8, 100.0)     # s
MAX_COORDINATE = 1e6         # m, of any placed vertex, position or region
MAX_MAGNITUDE = 1e15         # of any other number in a scene file (velocities, gravity, ...)
MAX_INTEGER = 2**31 - 1      # the engine's integers are int32
MAX_NESTING = 32             # tables and lists inside each other; a real scene needs 4


@contextlib.contextmanager
def lifted(on=True):
    """Inside the block the size limits are off (when on)."""
    global _lifted
    before, _lifted = _lifted, on or _lifted
    try:
        yield
    finally:
        _lifted = before


def check_size(count, limit, where, what):
    """SizeLimitError naming `where` when count > limit (unless lifted)."""
    if not _lifted and count > limit:
        raise SizeLimitError(f"{where}: {what} is more than the limit of {limit:,}")


def check_file_size(path, limit=None):
    """SizeLimitError for a file larger than limit (default MAX_FILE_BYTES), before it is read."""
    limit = limit or MAX_FILE_BYTES
    try:
        size = path.stat().st_size
    except OSError:
        return                       # the reader says what is wrong with it
    if not _lifted and size > limit:
        raise SizeLimitError(f"{path}: a file of {size / 2**20:,.0f} MB is more than the limit of "
                             f"{limit / 2**20:,.0f} MB")


def check_body_count(count, where):
    check_size(count, MAX_BODIES, where, f"{amount(count)} bodies")


def check_scene_tets(count, where):
    check_tets(count, where, f"{amount(count)} tets in all bodies together", "in a scene")


def check_tets(count, where, what, scope, limit=None):
    """SizeLimitError naming `where` when `count` tets (`what`: how the count came about) pass
    `limit` (default: tet_limit()), unless lifted. The message names the memory they need
    and the memory the limit comes from."""
    limit = tet_limit() if limit is None else limit
    if _lifted or count <= limit:
        return
    size, name = memory()
    raise SizeLimitError(f"{where}: {what} is more than the limit of {limit:,} tets {scope}: they need "
                         f"about {gigabytes(count * bytes_per_tet())} of memory, and the limit is "
                         f"{MEMORY_SHARE:.0%} of the {gigabytes(size)} of {name}")


def tet_limit():
    """The most tets a scene may have: as many as MEMORY_SHARE of memory() holds."""
    return int(MEMORY_SHARE * memory()[0] / bytes_per_tet())


def bytes_per_tet():
    return BYTES_PER_TET[runtime.current().get("precision", "f32")]


def memory():
    """(bytes, name) of the memory the engine's fields live in: the GPU's on CUDA, the host's
    otherwise (and on other GPU backends, which do not say: there it is only an upper bound)."""
    if runtime.current().get("arch") == "cuda":
        size = cuda_memory()
        if size:
            return size, "GPU memory (CUDA device 0)"
    return host_memory(), "host memory"


@functools.lru_cache(maxsize=None)
def host_memory():
    """Bytes of physical memory of this machine."""
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


@functools.lru_cache(maxsize=None)
def cuda_memory():
    """Bytes of memory of CUDA device 0 (the one Taichi uses), or None when the driver cannot say."""
    try:
        cuda = ctypes.CDLL(ctypes.util.find_library("cuda") or "libcuda.so.1")
        device, size = ctypes.c_int(), ctypes.c_size_t()
        if cuda.cuInit(0) or cuda.cuDeviceGet(ctypes.byref(device), 0) or \
                cuda.cuDeviceTotalMem_v2(ctypes.byref(size), device):
            return None
        return size.value
    except (OSError, AttributeError):
        return None


def gigabytes(count):
    """`count` bytes for a message, in MB or GB; of any size (amount())."""
    if count < 10**8:
        return f"{count / 1e6:,.0f} MB"
    return f"{count / 1e9:,.1f} GB" if count < 10**15 else f"{amount(count // 10**9)} GB"


def amount(count) -> str:
    """A count for a message: "22,978,239", or from 1e15 on "1.33e+60", cut to three digits.
    A count asked for by a resolution of 1e20 has 60 digits, unreadable, and past 1e308 a
    Python integer has no float to print it with."""
    count = int(count)
    if count < 10**15:
        return f"{count:,}"
    digits = str(count)
    return f"{digits[0]}.{digits[1:3]}e+{len(digits) - 1}"


def check_range(value, low, high, where, unit=""):
    """FemError unless low <= value <= high."""
    if not low <= value <= high:
        raise FemError(f"{where} must be in [{low:g}, {high:g}]{unit}, got {value:g}")


def nesting_depth(value) -> int:
    """How many tables and lists are inside each other in parsed TOML data (iterative: a
    deep value must not exhaust Python's stack)."""
    deepest, pending = 0, [(value, 0)]
    while pending:
        item, depth = pending.pop()
        if isinstance(item, dict):
            item = list(item.values())
        if isinstance(item, list):
            deepest = max(deepest, depth + 1)
            if depth + 1 <= MAX_NESTING:           # deeper is refused anyway
                pending += [(child, depth + 1) for child in item]
    return deepest


def check_nesting(value, where):
    if nesting_depth(value) > MAX_NESTING:
        raise FemError(f"{where}: tables or lists nested more than {MAX_NESTING} deep")
