"""What a step costs on a GPU (issue 36), in one run of a few minutes.

    python -m tools.gpu_measure OUT.md [--arch gpu] [--budget 400]     # from the repository's root
    python -m tools.gpu_measure OUT.md --arch cpu --quick              # tiny boxes: a check on a CPU

The cases are the benchmark's spinning, twisting box bars (examples/box50k.toml at 2k x k x k
cells, 10 k^3 tets; dt 0.02 s): k = 17, 27, 46 and 58, i.e. 49,130, 196,830, 973,360 and
1,951,120 tets (--quick: k = 3 to 6). For each it times the one-solve step (backward Euler,
one PCG solve) and the default step (trapezoidal, Newton): WARMUP steps, then --steps timed
ones, and reports the median ms/step and the mean CG iterations per step. Then, with Taichi's
kernel profiler on (which waits for every kernel, so those runs are not timed), the kernel
table (app/profile.py) of the smallest box and of the third (973k) for both steps, and each
step's achieved bandwidth where CUPTI can count bytes (a Taichi built with CUPTI; the PyPI
wheels are not, and then bytes are "n/a").

OUT.md gets the tables and OUT.json the numbers, rewritten after every case, so that a run
stopped early keeps what it measured. A case refused or failing (memory) is reported and the
others go on; once the budget (s) is spent the remaining cases are skipped, and said so. The
largest box runs last (its mesh and coarse matrices take the host longest to build).
"""

import argparse
import dataclasses
import json
import platform
import statistics
import sys
import time
import traceback
from pathlib import Path

import fem
import scenes
from app import device, profile

ROOT = Path(__file__).resolve().parents[1]
BOX = ROOT / "examples" / "box50k.toml"
SIZES = (17, 27, 46, 58)             # 2k x k x k cells: 49k, 197k, 973k, 2M tets
QUICK_SIZES = (3, 4, 5, 6)
PROFILED = (0, 2)                    # which sizes get a kernel table: box50k and the 973k box
WARMUP = 3                           # steps before timing: compiling, first touches
STEPS = profile.STEP_KINDS
# Peak DRAM bandwidth, GB/s, by a part of the device's name (vendors' data sheets).
PEAK_GB_S = {"H200": 4800, "H100 80GB HBM3": 3350, "H100 PCIe": 2000, "H100 NVL": 3900, "A100-SXM4-80GB": 2039}


def box_simulation(k):
    """The box of 2k x k x k cells (10 k^3 tets), its solver settings the scene's own."""
    scene = scenes.load_scene(str(BOX), overrides=[f"body.bar.mesh.cells=[{2 * k},{k},{k}]"])
    return fem.Simulation(scene)


def run_steps(sim, kind, steps):
    """From the scene's start, WARMUP then `steps` steps of `kind`; (ms per timed step, CG iterations per step)."""
    sim.reset()
    sim.settings = dataclasses.replace(sim.settings, **STEPS[kind])
    for _ in range(WARMUP):
        sim.step()
    ms, iterations = [], []
    for _ in range(steps):
        sim.step()
        ms.append(sim.last["wall_ms"])
        iterations.append(sim.last["solver_iters"])
    return ms, iterations


def time_case(k, steps):
    """{"tets", "one-solve": {...}, "default": {...}} of the box with k, timed without the profiler."""
    start = time.perf_counter()
    sim = box_simulation(k)
    case = {"k": k, "tets": sim.model.n_tets, "build_s": time.perf_counter() - start}
    for kind in STEPS:
        ms, iterations = run_steps(sim, kind, steps)
        case[kind] = {"ms_median": statistics.median(ms), "ms_min": min(ms), "ms_max": max(ms),
                      "cg_per_step": statistics.mean(iterations), "steps": steps}
    return case


def profile_case(k, steps):
    """{kind: the kernel table (app/profile.profile_steps)} of the box with k (Taichi must run
    with its profiler on)."""
    sim = box_simulation(k)
    return {kind: profile.profile_steps(sim, kind, WARMUP, steps) for kind in STEPS}


def bandwidth(rows, device_name):
    """(GB/s over the step's kernels, share of the device's peak or None); None without counted bytes."""
    counted = [r for r in rows if r["bytes"] is not None]
    if not counted:
        return None
    achieved = sum(r["bytes"] for r in counted) / sum(r["ms"] for r in counted) / 1e6
    peak = next((v for key, v in PEAK_GB_S.items() if key in (device_name or "")), None)
    return achieved, achieved / peak if peak else None


def markdown(results):
    m = results["machine"]
    lines = ["# GPU measurement (tools/gpu_measure.py)", "",
             f"Device: {m['device']} ({m['backend']}); host {m['host']}; Taichi {m['taichi']}, "
             f"{m['precision']}; {m['date']}; {m['minutes']:.1f} minutes.", "",
             "| tets | step | ms/step (median) | min-max | CG iterations/step | steps/s |",
             "|---:|---|---:|---:|---:|---:|"]
    for case in results["cases"]:
        if "error" in case:
            lines.append(f"| k = {case['k']} | either | {case['error']} | | | |")
            continue
        for kind in STEPS:
            r = case[kind]
            lines.append(f"| {case['tets']:,} | {kind} | {r['ms_median']:.2f} | {r['ms_min']:.2f}-{r['ms_max']:.2f} "
                         f"| {r['cg_per_step']:.1f} | {1000 / r['ms_median']:.0f} |")
    for name, kinds in results["profiles"].items():
        if "error" in kinds:
            lines += ["", f"## Kernel profile, {name}: {kinds['error']}"]
            continue
        for kind, p in kinds.items():
            replays = " (CUPTI counting bytes: kernels replayed, times not the plain step's)" \
                if m.get("bytes_counted") else ""
            lines += ["", f"## Kernel profile, {p['tets']:,} tets, {kind} step ({p['steps']} steps, "
                          f"{p['ms_median']:.2f} ms/step median with the profiler on){replays}", "",
                      profile.markdown(p["rows"], p["steps"], p["wall_ms"], top=25)]
            found = bandwidth(p["rows"], m["device"])
            lines += ["", "Launches: " + profile.launches_note(p) + "."]
            lines += ["", "Achieved bandwidth over the step's kernels: " + (
                "n/a (bytes need CUPTI, which this Taichi lacks)" if found is None else
                f"{found[0]:.0f} GB/s" + (f", {100 * found[1]:.0f} % of the device's peak" if found[1] else ""))]
    return "\n".join(lines) + "\n"


def write(results, out):
    results["machine"]["minutes"] = (time.time() - results["machine"]["started"]) / 60
    out.write_text(markdown(results))
    out.with_suffix(".json").write_text(json.dumps(results, indent=1))


def guarded(deadline, action):
    """action() unless the budget is spent; a failure is reported as what failed, not raised."""
    if time.perf_counter() > deadline:
        return {"error": "skipped: the time budget was spent"}
    try:
        return action()
    except Exception as error:              # one case failing (memory, a refusal) must not end the run
        traceback.print_exc()
        return {"error": f"{type(error).__name__}: {str(error)[:200]}"}


def measure_case(results, k, deadline, timed, out):
    """Time the box with k into results["cases"] (with the seconds it took), and write the summary."""
    start = time.perf_counter()
    case = guarded(deadline, lambda: timed(k))
    results["cases"].append({"k": k, **case, "seconds": time.perf_counter() - start})
    write(results, out)
    print(f"k = {k}: {case}", file=sys.stderr)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", help="the markdown summary (OUT.json beside it gets the numbers)")
    parser.add_argument("--arch", default="gpu", choices=["gpu", "cpu", "auto"])
    parser.add_argument("--precision", default="f32", choices=["f32", "f64"])
    parser.add_argument("--quick", action="store_true", help="tiny boxes and 3 steps (a check on a CPU)")
    parser.add_argument("--steps", type=int, help="timed steps per case (default 30; 3 with --quick)")
    parser.add_argument("--budget", type=float, default=400.0,
                        help="seconds after which the remaining cases are skipped (default 400)")
    args = parser.parse_args(argv)
    sizes, steps = (QUICK_SIZES, args.steps or 3) if args.quick else (SIZES, args.steps or 30)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    deadline = time.perf_counter() + args.budget
    backend = fem.init(args.arch, args.precision)
    found = device.describe(backend)
    results = {"machine": {"device": found["name"] or backend, "backend": backend, "host": platform.processor()
                           or platform.machine(), "taichi": ".".join(map(str, __import__("taichi").__version__)),
                           "precision": args.precision, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                           "started": time.time()},
               "cases": [], "profiles": {}}
    print(f"{results['machine']['device']} ({backend}): boxes k = {sizes}, {steps} steps each", file=sys.stderr)
    # The timings (profiler off), then the kernel tables, then the largest box: if it does not
    # fit in memory or in the budget, all else is measured. Its host-side build and first step
    # take about twice the 973k box's (the mesh, the coarse matrices): skipped when that would
    # not end within the budget.
    timed = lambda k: time_case(k, steps)                                  # noqa: E731
    for k in sizes[:-1]:
        measure_case(results, k, deadline, timed, out)
    fem.init(args.arch, args.precision, profile=True)          # restarts Taichi with its profiler
    results["machine"]["bytes_counted"] = profile.count_bytes()
    for index in PROFILED:
        k = sizes[index]
        name = f"box k = {k} ({10 * k ** 3:,} tets)"
        results["profiles"][name] = guarded(deadline, lambda: profile_case(k, min(steps, 10)))
        write(results, out)
    fem.init(args.arch, args.precision)                        # the profiler off again
    largest = sizes[-1]
    previous = results["cases"][-1].get("seconds")
    if previous and time.perf_counter() + 2.2 * previous > deadline:
        results["cases"].append({"k": largest, "error": f"skipped: about {2.2 * previous:.0f} s needed, "
                                                       f"more than the budget left"})
    else:
        measure_case(results, largest, deadline, timed, out)
    write(results, out)
    print(markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
