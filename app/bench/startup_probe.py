"""Where one start of `main.py simulate SCENE --steps 1` goes, measured inside a new process.

    python -m app.bench.startup_probe SCENE [simulate's options ...]

prints one JSON object: the seconds of Python's imports, starting Taichi, building the
Simulation (the scene read, the model and solver made), the first step, and within them the
seconds Taichi spent per kernel: translating its Python into Taichi's IR (`materialize`, every
start) and its first launch, which compiles the IR or loads it from the offline cache (Taichi
1.7's CPU cache keeps LLVM IR, so LLVM still compiles it into machine code). A kernel with
several template arguments (a field, a switch) is a variant each. `app/bench/startup.py` runs it.
"""

import argparse
import json
import sys
import time
from collections import defaultdict

STARTED = time.perf_counter()


def instrument():
    """{kernel: [translate_s, compile_s, variants]}, filled as kernels compile and first launch."""
    from taichi.lang import kernel_impl

    kernels = defaultdict(lambda: [0.0, 0.0, 0])
    launched = set()
    materialize, launch = kernel_impl.Kernel.materialize, kernel_impl.Kernel.launch_kernel

    def timed_materialize(kernel, key=None, args=None, arg_features=None):
        # Taichi calls it at every launch; it returns at once for a kernel compiled already
        if (key or (kernel.func, 0, kernel.autodiff_mode)) in kernel.compiled_kernels:
            return materialize(kernel, key=key, args=args, arg_features=arg_features)
        start = time.perf_counter()
        try:
            return materialize(kernel, key=key, args=args, arg_features=arg_features)
        finally:
            row = kernels[kernel.func.__name__]
            row[0] += time.perf_counter() - start
            row[2] += 1

    def timed_launch(kernel, t_kernel, *args):
        if id(t_kernel) in launched:
            return launch(kernel, t_kernel, *args)
        launched.add(id(t_kernel))
        start = time.perf_counter()
        try:
            return launch(kernel, t_kernel, *args)
        finally:
            kernels[kernel.func.__name__][1] += time.perf_counter() - start

    kernel_impl.Kernel.materialize, kernel_impl.Kernel.launch_kernel = timed_materialize, timed_launch
    return kernels


def parse(argv):
    """SCENE and the options of `simulate` that change what a start compiles."""
    parser = argparse.ArgumentParser(prog="python -m app.bench.startup_probe")
    parser.add_argument("scene")
    parser.add_argument("--contact", action="store_true")
    parser.add_argument("--precision", choices=("f32", "f64"), default="f32")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--arch", default="cpu")
    return parser.parse_args(argv)


def main(argv):
    import fem          # the engine's imports, Taichi's among them
    import scenes

    imported = time.perf_counter()
    args = parse(argv)
    kernels = instrument()
    fem.init(args.arch, args.precision, profile=args.profile)
    started = time.perf_counter()
    sim = fem.Simulation(scenes.load_scene(args.scene, contact=args.contact))     # as `simulate` builds it
    built = time.perf_counter()
    sim.step()
    stepped = time.perf_counter()
    translate = sum(row[0] for row in kernels.values())
    compile_ = sum(row[1] for row in kernels.values())
    slowest = sorted(kernels.items(), key=lambda item: -(item[1][0] + item[1][1]))
    print(json.dumps({
        "imports_s": imported - STARTED, "init_s": started - imported, "build_s": built - started,
        "first_step_s": stepped - built, "total_s": stepped - STARTED,
        "translate_s": translate, "compile_s": compile_,
        "kernels": len(kernels), "variants": sum(row[2] for row in kernels.values()),
        "slowest": [{"kernel": name, "translate_s": row[0], "compile_s": row[1], "variants": row[2]}
                    for name, row in slowest[:10]]}))


if __name__ == "__main__":
    main(sys.argv[1:])
