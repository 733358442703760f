"""The step's tunables, timed side by side (issue 36): which chunk sizes and unrolling a GPU wants.

    python -m tools.gpu_tune OUT.json [--arch gpu] [--sizes 17,46] [--steps 20] [SETTING ...]
    python -m tools.gpu_tune OUT.json --sizes 17,46 GPU_CAPACITY_LOOPS=1         # the next GPU run's question
    python -m tools.gpu_tune OUT.json --arch cpu --sizes 2 --steps 1 CHUNK=16,CG_UNROLL=3

A SETTING is NAME=VALUE[,NAME=VALUE...] over TUNABLES below; the defaults run first, then each
setting, each on every box of tools/gpu_measure.py (2k x k x k cells, 10 k^3 tets) with the
solver built anew, timed as gpu_measure times a case (median ms/step and CG iterations of both
steps). OUT.json is rewritten after every case, so a run stopped early keeps what it measured;
a summary table goes to stdout.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import fem
import fem.coarse
import fem.implicit.linear
import fem.implicit.preconditioner
import fem.pool
import fem.reduce
import fem.runtime
from tools.gpu_measure import time_case

TUNABLES = {"CHUNK": fem.reduce, "GPU_CHUNK": fem.reduce, "FAN_IN": fem.reduce, "COARSE_PARTS": fem.coarse,
            "CG_UNROLL": fem.implicit.linear, "TWO_LEVEL_VERTICES": fem.implicit.preconditioner, "GPU_GRID_BLOCKS": fem.runtime,
            "GPU_CAPACITY_LOOPS": fem.runtime}
ZERO_ALLOWED = {"GPU_GRID_BLOCKS": "0 (Taichi's own grid)", "GPU_CAPACITY_LOOPS": "0 (off)"}


def parse(setting):
    """"CHUNK=32,CG_UNROLL=4" -> {"CHUNK": 32, "CG_UNROLL": 4}."""
    try:
        pairs = {name: int(value) for name, value in (part.split("=", 1) for part in setting.split(","))}
    except ValueError:
        refuse(f"{setting!r} is not NAME=INTEGER[,NAME=INTEGER...]")
    unknown = set(pairs) - set(TUNABLES)
    if unknown:
        refuse(f"unknown tunable {sorted(unknown)}; known: {sorted(TUNABLES)}")
    for name, value in pairs.items():
        if value < 1 and not (name in ZERO_ALLOWED and value == 0):
            zero = f"{ZERO_ALLOWED[name]} or " if name in ZERO_ALLOWED else ""
            refuse(f"{name}={value}: must be {zero}a positive integer")
    return pairs


def refuse(why):
    """Bad input: one error line, exit 2."""
    print(f"error: {why}", file=sys.stderr)
    raise SystemExit(2)


def apply(values, defaults, arch=None):
    """Set the tunables to the defaults, then to `values`; the next Simulation builds with them
    (fem.init on `arch` restarts Taichi when GPU_GRID_BLOCKS changed: its kernels compile with it)."""
    for name, value in {**defaults, **values}.items():
        setattr(TUNABLES[name], name, value)
    fem.pool.clear()                    # solvers kept from a case before were built with other values
    if arch:
        fem.init(arch, "f32")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out")
    parser.add_argument("settings", nargs="*", help="NAME=VALUE[,NAME=VALUE...]")
    parser.add_argument("--arch", default="gpu", choices=["gpu", "cpu"])
    parser.add_argument("--sizes", default="17,46", help="the boxes' k, comma-separated (default 17,46)")
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_intermixed_args(argv)
    settings = [{}] + [parse(s) for s in args.settings]
    sizes = [int(k) for k in args.sizes.split(",")]
    backend = fem.init(args.arch, "f32")
    defaults = {name: getattr(module, name) for name, module in TUNABLES.items()}
    results = {"backend": backend, "defaults": defaults, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               "cases": []}
    out = Path(args.out)
    for k in sizes:
        for values in settings:
            apply(values, defaults, args.arch)
            case = {"setting": values, **time_case(k, args.steps)}
            results["cases"].append(case)
            out.write_text(json.dumps(results, indent=1))
            print(" ".join(f"{n}={v}" for n, v in values.items()) or "defaults", case["tets"],
                  *(f"{kind} {case[kind]['ms_median']:.2f} ms ({case[kind]['cg_per_step']:.1f} CG)"
                    for kind in ("one-solve", "default")), sep=" | ", flush=True)
    apply({}, defaults)
    return 0


if __name__ == "__main__":
    sys.exit(main())
