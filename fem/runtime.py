"""Starting Taichi: backend (`arch`) and floating-point precision, chosen once per process."""

import contextlib
import functools
import io
import linecache
import os
import sys
import textwrap
import traceback
import types

import taichi as ti

from fem import environment, launch, quick_ops
from fem.errors import FemError

ARCHES = ("auto", "cpu", "gpu")
# Taichi's offline cache drops its least recently used kernels beyond this size (its own
# default, 100 MB, is about 3000 kernels: a few scenes in two precisions and the tests
# overflow it, and the next start of a scene compiles again, seconds instead of one).
OFFLINE_CACHE_BYTES = 512 * 2**20
PRECISIONS = ("f32", "f64")
# Blocks (of 128 threads) that a GPU loop runs when its length is known only on the device (every
# loop over the vertices or tets in use). Taichi's default, 2 x the blocks an SM can hold x the
# SMs, is 8,448 on an H100: over a million threads for any loop, and a loop that adds into one
# number (PCG's r.z, p.Ap) then adds every thread's partial at its end, about 70 us whatever the
# mesh. 0: Taichi's default. Measured (docs/gpu.md, tools/gpu_tune.py).
GPU_GRID_BLOCKS = 2048
# On a GPU, the PCG iteration's loops (fem/implicit/linear.py, the coarse level's passes and every
# sum in stages, fem/reduce.py) run over their fields' capacity, a constant when the kernel
# compiles, when this is 1: Taichi then sizes such a loop's grid to it (at most GPU_GRID_BLOCKS),
# where a loop whose length only the device knows always runs GPU_GRID_BLOCKS blocks, and the
# items past the count in use are skipped. A small mesh pays for a large grid (docs/gpu.md:
# halving the grid took box50k's one-solve step from 4.9 to 3.1 ms on an H200). 0 until measured
# on a GPU (`tools/gpu_tune.py ... GPU_CAPACITY_LOOPS=1`); a CPU ignores it.
GPU_CAPACITY_LOOPS = 0
# Where Taichi's kernel profiler works: on Vulkan (Mesa's llvmpipe at least) writing a field
# with it on is a segmentation fault.
PROFILED_BACKENDS = ("x64", "arm64", "cuda")
_current = {}


def init(arch="cpu", precision="f32", debug=False, restart=False, profile=False):
    """Start Taichi on `arch` ("cpu", "gpu" or "auto": a GPU backend when one exists, else CPU)
    with `precision` ("f32" or "f64") as the float type of every field; `profile`: with Taichi's
    kernel profiler on (every kernel is timed, and waited for: a little slower).

    Returns the backend's name. Calling it again with the same settings keeps Taichi
    running, with every kernel compiled so far (fem/pool.py); with other settings, or
    `restart=True`, it restarts Taichi, which invalidates every field made before.
    """
    if arch not in ARCHES:
        raise FemError(f"arch must be one of {ARCHES}, got {arch!r}")
    if precision not in PRECISIONS:
        raise FemError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    # auto takes CUDA only: a Vulkan "GPU" may be Mesa's software driver, slower than the CPU backend.
    # gpu never probes OpenGL: on a machine without it, Taichi's probe ends the process (segfault).
    settings = (arch, precision, debug)
    running = _current.get("runtime") is ti.lang.impl.get_runtime()
    if (not restart and running and _current.get("settings") == settings and _current.get("profile") == profile
            and _current.get("grid") == GPU_GRID_BLOCKS):
        return _current["arch"]              # running as asked (and nobody called ti.init since)
    if environment.problems():
        raise FemError(environment.problems()[0])
    brief_source_positions(not debug)
    remember_sources()
    quick_ops.install()
    launch.install()
    announce_compiling()
    wanted = {"cpu": ti.cpu, "gpu": [ti.cuda, ti.metal, ti.vulkan], "auto": ti.cuda}[arch]
    fp = ti.f32 if precision == "f32" else ti.f64
    ignore_taichi_arch_variable(arch)
    cache, note = environment.offline_cache_folder()
    if cache is None:
        raise FemError(note)
    if note:
        print(f"warning: {note}", file=sys.stderr)
    # Taichi prints a banner on stdout; keep stdout for our own output
    with contextlib.redirect_stdout(io.StringIO()), taichi_variables_reported():
        ti.init(arch=wanted, default_fp=fp, default_ip=ti.i32, debug=debug, offline_cache=True,
                offline_cache_file_path=cache, offline_cache_max_size_of_files=OFFLINE_CACHE_BYTES,
                log_level=ti.ERROR, kernel_profiler=profile, saturating_grid_dim=GPU_GRID_BLOCKS)
    backend = ti.lang.impl.current_cfg().arch.name
    if arch == "gpu" and backend in ("x64", "arm64"):
        raise NoGpuError("arch 'gpu': no GPU backend found on this machine ('cpu' or 'auto' run without one)")
    if profile and backend not in PROFILED_BACKENDS:
        ti.reset()
        _current.clear()
        raise FemError(f"the kernel profiler (--profile) runs on the CPU and CUDA only, not on {backend}: "
                       f"Taichi 1.7's profiler there ends the process at the first field written; "
                       f"profile with --arch cpu, or on an NVIDIA GPU")
    _current.update(arch=backend, precision=precision, settings=settings, profile=profile, grid=GPU_GRID_BLOCKS,
                    runtime=ti.lang.impl.get_runtime())
    return backend


class NoGpuError(FemError):
    """arch "gpu" asked for on a machine where Taichi finds no GPU backend."""


def ignore_taichi_arch_variable(arch):
    """Taichi's TI_ARCH would override the `arch` asked for here (TI_ARCH=opengl on a machine
    without OpenGL ends the process with a segfault; TI_ARCH=xyz aborts it): the argument
    wins, and the variable is dropped with a warning."""
    value = os.environ.pop("TI_ARCH", None)
    if value is not None:
        print(f"warning: environment variable TI_ARCH={value[:40]!r} ignored: the backend is the "
              f"arch asked for ({arch!r})", file=sys.stderr)


@contextlib.contextmanager
def taichi_variables_reported():
    """A TI_* environment variable Taichi cannot use (TI_DEBUG=yes) is a FemError naming the
    variables set, not Taichi's traceback."""
    try:
        yield
    except (ValueError, KeyError, TypeError) as error:
        names = sorted(name for name in os.environ if name.startswith("TI_"))
        if not names:
            raise
        raise FemError(f"Taichi cannot start with the environment variables {', '.join(names)} "
                       f"({type(error).__name__}: {str(error)[:100]}); unset them") from None


def brief_source_positions(on=True):
    """Taichi formats a source excerpt with a caret line for every node of every kernel it
    translates, in case that node fails to compile. It does so even when the offline cache
    then supplies the compiled kernel, and the formatting is about half of a warm start.
    On: only "File ..., line N, in kernel" is kept (the excerpt is shown with --debug)."""
    from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext as Context

    if not hasattr(Context, "full_pos_info"):
        Context.full_pos_info = Context.get_pos_info
    Context.get_pos_info = _brief_pos_info if on else Context.full_pos_info


def remember_sources():
    """Taichi reads a ti.func's source again (inspect's tokeniser) and re-wraps its lines every
    time a kernel calls it, even when the offline cache then supplies the compiled kernel: a
    fifth of a warm start. A function's source does not change while the process runs, so
    each is read once."""
    from taichi.lang import kernel_impl

    if hasattr(kernel_impl.getsourcelines, "cache_info"):      # remembered already
        return
    remember = functools.lru_cache(maxsize=None)
    kernel_impl.getsourcefile = remember(kernel_impl.getsourcefile)
    kernel_impl.getsourcelines = remember(kernel_impl.getsourcelines)
    kernel_impl.textwrap = types.SimpleNamespace(fill=remember(textwrap.fill), dedent=textwrap.dedent)


def quick_declarations():
    """Declaring a kernel or a field costs Taichi a look at the source of the line that declares it:
    whether a kernel is declared in a class (`_inside_class`: inspect resolves the module of the
    frame, 1.5 ms a kernel), and the whole stack of a field's declaration, kept for an error
    message. Each kernel here is checked from the same line through linecache, and a field keeps
    the three frames that declared it. Called before any module with kernels is imported."""
    from taichi.lang import impl, kernel_impl, matrix, snode

    if getattr(kernel_impl._inside_class, "quick", False):
        return
    launch.install_data_oriented()
    patterns = kernel_impl._KERNEL_CLASS_STACKFRAME_STMT_RES

    def inside_class(level_of_class_stackframe):
        try:
            frame = sys._getframe(level_of_class_stackframe)
        except ValueError:
            return False
        line = linecache.getline(frame.f_code.co_filename, frame.f_lineno).strip()
        return any(pattern.match(line) for pattern in patterns)

    def declared_at(stacklevel=1):
        try:
            frame = sys._getframe(1 + stacklevel)
        except ValueError:
            frame = None
        return "".join(traceback.format_list(traceback.extract_stack(frame, limit=3)))

    inside_class.quick = True
    kernel_impl._inside_class = inside_class
    for module in (impl, matrix, snode):
        module.get_traceback = declared_at


# Who hears of each kernel that is about to compile (compile_listeners, announce_compiling).
_listeners = []


def compile_listeners():
    """The list of functions called with a kernel's name just before Taichi translates and compiles it:
    each kernel the first time it runs, and again for each new set of template arguments (a start
    spends most of its time there: docs/benchmark.md). Append to it, and remove what you added."""
    return _listeners


def announce_compiling():
    """Tell compile_listeners() before Taichi materialises a kernel: translates its Python into
    Taichi's IR, which the first launch then compiles or loads from the offline cache. Called
    between two kernels, never inside one, so a listener may launch kernels that are compiled
    already (the window draws a frame)."""
    from taichi.lang import kernel_impl

    if hasattr(kernel_impl.Kernel.materialize, "announced"):
        return
    materialize = kernel_impl.Kernel.materialize

    def announced(kernel, key=None, args=None, arg_features=None):
        # Taichi calls it at every launch; it returns at once for a kernel compiled already
        if (key or (kernel.func, 0, kernel.autodiff_mode)) not in kernel.compiled_kernels:
            for listener in list(_listeners):
                listener(kernel.func.__name__)
        return materialize(kernel, key=key, args=args, arg_features=arg_features)

    announced.announced = True
    kernel_impl.Kernel.materialize = announced


def _brief_pos_info(context, node):
    return f'File "{context.file}", line {node.lineno + context.lineno_offset}, in {context.func.func.__name__}:\n'


def current():
    """{"arch": backend name, "precision": "f32"|"f64"} of the running Taichi, {} before init."""
    return {key: _current[key] for key in ("arch", "precision") if key in _current}


def cache_folder():
    """The folder of Taichi's offline cache, as the running Taichi uses it."""
    return ti.lang.impl.current_cfg().offline_cache_file_path


def requested():
    """(arch, precision, debug) as `init` was last asked for them; None before init."""
    return _current.get("settings")


# On the CPU every parallel loop pays ~50-100 us to wake Taichi's thread pool (measured on
# 2-core machines), more than a small loop takes on one thread; below these sizes loops run serially.
PARALLEL_MIN = {"tets": 8000, "vertices": 30000}


def on_cpu():
    """True when Taichi runs on the CPU (x64 or arm64)."""
    return _current.get("arch") in ("x64", "arm64")


def capacity_loops():
    """True when the PCG iteration's loops run over their fields' capacity (GPU_CAPACITY_LOOPS, on a GPU)."""
    return bool(GPU_CAPACITY_LOOPS) and not on_cpu()


def serial_loops(count, kind):
    """True when a CPU loop over `count` tets or vertices (kind) is faster on one thread."""
    return on_cpu() and count < PARALLEL_MIN[kind]


def precision():
    """"f32" or "f64": the float type the fields use (f32 before init)."""
    return "f64" if _current.get("precision") == "f64" else "f32"


def epsilon():
    """Machine epsilon of the float type the fields use (f32 before init)."""
    return 2.0 ** -52 if precision() == "f64" else 2.0 ** -23


def has_f64_trigonometry():
    """True where the backend computes sin and cos in float64 (CPU and CUDA; not Vulkan or Metal)."""
    return _current.get("arch") in ("x64", "arm64", "cuda")
