"""What a description may ask for: sizes checked before anything is allocated, and ranges
of physical numbers inside which the arithmetic stays finite.

A size (tets, bodies, bytes of a file, legs of a dome) over its limit is a
`SizeLimitError`, which `lifted()` (the command line's --allow-large) switches off:
such a description is more likely a slip than a wish, and would take the machine's
whole memory before failing. A number outside its range (E = 1e308, dt = 1e-300,
a body placed 1e308 m away) is a plain FemError: no real scene needs it, and the
squares and products of the step would overflow.
"""

import contextlib

from fem.errors import FemError, SizeLimitError

# Sizes, each lifted by lifted().
MAX_BODIES = 256             # the coarse preconditioner grows with the square of the body count
MAX_SCENE_TETS = 2_000_000   # all bodies together (a comparison doubles a scene)
MAX_FILE_BYTES = 256 * 2**20  # a mesh file; a million-tet MEDIT file is about 60 MB
# A TOML scene file: the parser takes about 25 times a file's size in memory (a 240 MB file:
# 6 GB, then MemoryError), and a scene names its meshes' files rather than holding them.
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
    check_size(count, MAX_BODIES, where, f"{count:,} bodies")


def check_scene_tets(count, where):
    check_size(count, MAX_SCENE_TETS, where, f"{count:,} tets in all bodies together")


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
