"""The benchmark's report: results.md (the headline, the targets and what limits them, the
preconditioners, one table per scene), results.json (every number) and the plot."""

import json
from pathlib import Path

from app.bench.conclusions import (ORDER_MARGIN, TIME_RESOLUTION, baseline, corotation_cost, direct_comparison, find,
                                   fmt, final_error, frontier, goal_dt)
from app.bench.measure import PRECONDITIONER_TOLERANCE
from app.bench.plan import (BASELINE_TOLERANCE, ERROR_GOAL, FULL_BUDGET_S, FULL_CHECKPOINTS, INTEGRATORS,
                            MIN_REFERENCE_ORDER, QUICK, QUICK_DURATION, REFERENCE_ORDER, REFERENCE_REFINEMENT,
                            REFERENCE_SETTINGS, SECOND_ORDER, TARGET_SCENE, sci, step_name)
from app import profile
from app.bench import contact_report
from app.bench.plot import numbers, plot
from app.files import atomic_open
from fem.implicit.preconditioner import TWO_LEVEL_VERTICES

# What `write` names its files: in --out, and as the committed pages in docs/ (`bench --docs`).
RESULT_FILES = {"json": "results.json", "md": "results.md", "plot": "accuracy_vs_time.png"}
DOCS = Path(__file__).resolve().parents[2] / "docs"
# In docs/ the plot's numbers go beside it too, as `figures` writes them (tests/test_committed_figures.py
# compares them with a fresh redraw: a new benchmark replaces both or the suite says so).
DOCS_FILES = {"json": "benchmark.json", "md": "benchmark.md", "plot": "accuracy_vs_time.png",
              "numbers": "accuracy_vs_time.json"}


# ---------------------------------------------------------------- writing

def explanation(results):
    """Two paragraphs: the reference and what its error floor means; the columns."""
    plan = results["plan"]
    settings = REFERENCE_SETTINGS
    integrator, order = INTEGRATORS[settings["integrator"]], REFERENCE_ORDER
    reference = (
        f"Each run starts from the same state and runs to the last checkpoint. **The reference** is corotational "
        f"{integrator} (order {order}) at dt_ref = the scene's dt / {REFERENCE_REFINEMENT}: Newton until every "
        f"body's gradient is under {sci(settings['tolerance'])} of the step's own terms, or an iteration changes "
        f"its velocity by under {sci(settings['newton_tolerance'])} of its size (at most {settings['max_newton']} "
        f"iterations), PCG to {sci(settings['tolerance'])}, rotations certified to 1e-12 rad, in float64 whatever "
        "the variants' precision (so its timings are f64's); its first step, with no history yet, is backward "
        f"Euler's. Its own error is C dt_ref^p: *{integrator} reference at 2 dt_ref* and *at 4 dt_ref*, the same at "
        "twice and four times that dt, differ from each other 2^p times as much as the first differs from the "
        "reference, which gives p, the reference's own order (*its order*). The *reference floor*, its error, is its "
        f"distance to the run at 2 dt_ref over 2^p - 1 (3 for p = {order}), p taken at most {order} and at least "
        f"{MIN_REFERENCE_ORDER:g} (ground contact, an impulsive start or a torsional wave make it converge more "
        "slowly on some scenes). The error axis bottoms out there: a measured error is the true one give or take "
        f"the floor, so a run meets the goal of {100 * ERROR_GOAL:g} % of the scene size only when its error plus "
        "the floor does. (A backward-Euler reference at the same dt_ref, first order, had a floor as large as that "
        "distance, close to the smallest errors of the dt axis on the spinning bars.) *Observed order*: the slope "
        f"of log error against log dt over a dt axis (least squares, leaving out errors under {ORDER_MARGIN} times "
        "the floor): about 1 for backward Euler and 2 for BDF2 where dt resolves the motion.")
    columns = (
        "*step*: Newton (iterated until the velocity settles to the scene's newton_tolerance) or single (one "
        "linear solve with the rotations of the step's start); a linear body's step is exact either way. "
        "*s/sim s*: wall seconds per simulated second, ms/step / dt / 1000 (compares runs at different dt); "
        f"*ms/step*: wall time per step (median, min-max) after {plan['warmup_steps']} warm-up steps, "
        "Taichi kernels compiled beforehand; *Newton*: Newton iterations per step and *iters*: linear solver "
        "iterations per step (means); *ns/tet/iter*: a step's solve time per iteration and tet; *rot ms*: "
        "rotation extraction per step; *halvings*: line-search step halvings and *E-limited*: bodies whose "
        "solve failed, so that the safeguard trimmed their step or took it again by backward Euler, both summed over the run; *B/tet*: memory of the solver's data (Taichi "
        "fields of model, state and solver; for the direct solver the matrix and its factor); *err t*: RMS "
        "vertex distance to the reference at time t, divided by the bounding-box diagonal; *vol*: largest "
        "|volume / rest volume - 1| of any body; *energy*: (kinetic + elastic) energy at the end over its "
        "start value, minus 1. A blank (–) error: the variant would have taken longer than its time budget "
        f"({plan['budget_s']:g} s) and stopped early.")
    return reference + "\n\n" + columns


def is_quick(results):
    """Whether the results are a quick run's (plan.QUICK): results from before the flag are full runs'."""
    return results.get("plan", {}).get("quick", False)


def quick_scope(results):
    """What a quick run measured, and what it cannot conclude: the paragraph at the top of its report."""
    plan, scenes = results["plan"], results["scenes"]
    rows = [r for s in scenes for r in s["variants"] if r["solver"] != "reference"]
    stopped = sum(r["stopped_early"] for r in rows)
    checkpoints = " and ".join(f"{t:g}" for t in scenes[0]["checkpoints"]) if scenes else "–"
    return (f"**A quick run** (`bench --quick`): {len(scenes)} scene{'s' * (len(scenes) != 1)} "
            f"({', '.join(s['name'] for s in scenes)}), "
            f"positions compared with the reference at t = {checkpoints} s, each variant given {plan['budget_s']:g} s "
            f"of wall time ({stopped} of the {len(rows)} variants stopped early, without an error), and none of the "
            "full run's start-up, stiff bar, kernel profile or contact measurements. It shows that the benchmark "
            "runs on this machine and what each variant costs and how far it is from the reference on these "
            "scenes. It cannot conclude what the full run does: which settings are on the accuracy/time "
            f"frontier across the scenes, whether Newton pays, the speed targets (set on {TARGET_SCENE}, epcot, "
            "the stiff bar and the pile), or any cost smaller than the spread of timings from run to run "
            f"(about {100 * TIME_RESOLUTION:g} %). For those, run `bench` without --quick or read docs/benchmark.md, "
            "the committed full run.")


def quick_note():
    """The full report's paragraph on `bench --quick` (docs/benchmark.md is a full report)."""
    return (f"**`bench --quick`** runs {len(QUICK.scenes)} scenes ({', '.join(QUICK.scenes)}) to "
            f"t = {QUICK.checkpoints[-1]:g} s instead of {FULL_CHECKPOINTS[-1]:g} s, with {QUICK.budget_s:g} s of "
            f"wall time per variant instead of {FULL_BUDGET_S:g} s (variants that need more stop early and get no "
            "error), and none of the start-up, stiff bar, kernel profile or contact measurements; it takes "
            f"{QUICK_DURATION}. It checks that the benchmark runs and gives each variant's time and error on those "
            "scenes; its report says so at the top and leaves out what it cannot conclude: the frontier, whether "
            "Newton pays, the speed targets, and costs within the timing noise.")


def markdown(results):
    m, lines, quick = results["machine"], [], is_quick(results)
    lines += ["# What accuracy costs in time" + (": a quick run" if quick else ""), ""]
    if quick:
        lines += [quick_scope(results), ""]
    lines += [f"- {line}" for line in results["headline"]]
    lines += ["", f"Machine: {m['cpu']}, {m['cores']} cores (load average {m['load_average']:.1f} at the start)"
              + (f", GPU {m['gpu']}" if m.get("gpu") else "") + f"; Taichi {m['taichi']} on {m['backend']}, "
              f"{m['precision']}; direct solvers {m['direct_solver']}; Python {m['python']}; {m['date']}; "
              f"{m['bench_minutes']:.1f} minutes.", "", explanation(results), ""]
    if not quick:
        lines += [quick_note(), ""]
    lines += targets(results)
    lines += startup_table(results)
    lines += preconditioner_table(results)
    lines += kernel_profile(results)
    lines += contact_cost(results) + contact_report.piles(results)
    lines += ["## Summary", "",
              f"Corotational backward Euler, PCG {sci(BASELINE_TOLERANCE)}; time in wall seconds per simulated "
              "second, errors at the last checkpoint; the largest dt of the dt axis whose error plus the floor is "
              "within the goal.", "",
              "| scene | tets | dt (s) | reference floor | Newton s/sim s | single s/sim s | Newton error | "
              "single error | largest dt within goal, Newton | single | corotation's extra cost, single | "
              "Newton | direct |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in results["scenes"]:
        newton, single = baseline(s, "corotational", "newton"), baseline(s, "corotational", "single")
        lines.append(
            f"| {s['name']} | {s['tets']} | {s['dt']:g} | {s['reference_floor']:.1e} "
            f"| {newton['s_per_sim_s']:.3g} | {single['s_per_sim_s']:.3g} "
            f"| {fmt(final_error(newton), '.1e')} | {fmt(final_error(single), '.1e')} "
            f"| {fmt(goal_dt(s, 'newton'), 'g', 'none')} | {fmt(goal_dt(s, 'single'), 'g', 'none')} "
            f"| {corotation_cost(s, 'single'):+.0f} % | {corotation_cost(s, 'newton'):+.0f} % "
            f"| {corotation_cost(s, 'single', 'direct'):+.0f} % |")
    lines += integrator_table(results["scenes"])
    for s in results["scenes"]:
        times = [f"err {t:g} s" for t in s["checkpoints"]]
        lines += ["", f"## {s['name']}", "",
                  f"{s['description']} {s['tets']} tets, {s['vertices']} vertices, scene dt {s['dt']:g} s, "
                  f"dt_ref {s['reference_dt']:g} s, reference floor {s['reference_floor']:.1e} (its distance to the "
                  f"run at 2 dt_ref, {s['reference_difference']:.1e}, over 2^p - 1; its own order "
                  f"{s['reference_order']:.2f}).", "",
                  "| variant | step | dt (s) | s/sim s | ms/step | min-max | Newton | iters | ns/tet/iter | rot ms "
                  "| halvings | E-limited | B/tet | " + " | ".join(times) + " | vol | energy |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|" + "---:|" * len(times)
                  + "---:|---:|"]
        for r in s["variants"]:
            lines.append(
                f"| {r['name']} | {step_name(r)} | {r['dt']:g} "
                f"| {r['s_per_sim_s']:.3g} | {r['ms_median']:.3g} | {r['ms_min']:.3g}-{r['ms_max']:.3g} "
                f"| {fmt(r.get('newton_per_step'), '.2g')} | {fmt(r.get('iters_per_step'))} "
                f"| {fmt(r.get('ns_per_tet_iter'), '.0f')} | {r['rotation_ms']:.3g} "
                f"| {fmt(r.get('line_search_steps'), 'd')} | {fmt(r.get('energy_limited'), 'd')} "
                f"| {r['bytes_per_tet']:.0f} | " + " | ".join(fmt(e, ".2e") for e in r["errors"].values())
                + f" | {r['volume_drift']:.2e} | {fmt(r['energy_drift'], '+.2e')} |")
        lines += ["", direct_split(s)]
        if not quick:
            lines += ["", "Frontier (no variant is both faster per simulated second and more accurate): "
                      + ", ".join(frontier(s)) + "."]
    lines += ["", "![error against wall time per simulated second](accuracy_vs_time.png)", ""]
    return "\n".join(lines)


# What limits each speed target that a run does not meet (profiles taken on the 2-core machine).
LIMITS = {
    "warm": "a warm start of epcot (3.6 s, 2026-11-30): Python's imports about 0.5 s (Taichi's 0.26), starting "
            "Taichi 0.2 s, building the Simulation 0.5 s, the first Newton step 2.4 s. Most of it is the 28 kernels' "
            "two stages that run even when the offline cache has them: Taichi's frontend translating their Python "
            "(1.1 s; 1.9 s until Taichi's small-matrix operations were built straight from Python, "
            "fem/quick_ops.py; the energy projection's after_step 0.25 s), and loading them (1.55 s): Taichi 1.7's "
            "CPU backend caches LLVM IR, not machine code, and runs LLVM's O3 passes and code generation on every "
            "module again at each load (its jit_cpu.cpp; nothing in its configuration changes that). 2 x Taichi's "
            "start needs a cache of machine code or far less kernel code",
    "rotation": "on box50k, reading a tet's corners and Bm, forming F and writing Bm R^T and the quaternion "
                "alone takes about 12 ns/tet on 2 cores; started from the last step's turn, one certified "
                "Newton step on the polar decomposition finds R (two from the last R alone), and its scalar "
                "arithmetic (F R^T, the Hessian's adjugate, the error bound) takes the rest: 15 ns/tet leaves "
                "no room for it on this machine",
    "fixed": "rotation extraction, once per step (and once per line-search trial with Newton). The worst "
             "scene is box10k, 1.1 of 5.3 ms: there the rotation pass takes about 100 ns/tet, where box50k's "
             "takes 50, because on this virtual machine a parallel loop of about a millisecond mostly runs on "
             "one thread (the second vCPU takes about that long to wake): box10k's pass takes 0.95 ms on "
             "average with two threads, 0.98 ms with one, and 0.48 ms at best",
    "box50k": "the extrapolated first guess and the two-level preconditioner leave about 8 PCG iterations at "
              "1e-3 (24 with block Jacobi from v_n), each about 1.1 ms (the coarse level adds 0.25 ms to block "
              "Jacobi's 0.9); the rest is the step's fixed work, about 6 ms: rotations 2.5, the first product "
              "and the start of PCG 1, the gradient 0.9, the block-Jacobi build 0.3 (1 ms, one step in four), "
              "and a dozen small passes; the machine's spread between runs is about 10 %",
    "newton": "1.4 Newton iterations a step at 1e-3 (BDF2, from the extrapolated guess), each with its own "
              "PCG solve and a line-search trial with its own rotation extraction, then energy and gradient "
              "in one pass (float64 sums); R(x_n) is the last step's. Kernel profile of a box50k Newton step "
              "(about 42 ms on a slow run): rotations 7.6 ms (2.4 passes: the first iterate and each trial), "
              "energy and gradient 9 (the first iterate's and each trial's), PCG 17 (about 10 iterations), "
              "the block-Jacobi build 1.5, the safeguards 1. Tried: blocks rebuilt only when stale (as the one-solve step "
              "does) need 14.7 -> 22.3 PCG iterations a step on epcot, as the twist term moves with the "
              "stretch; a tighter forcing term (0.03) saves half a Newton iteration on box50k and costs as "
              "much in PCG. Newton buys the promise that energy never rises, not accuracy",
    "stiff": "as box50k: iterations (about 11, from 41 with block Jacobi) and the step's fixed work",
    "direct": "the matrix-free step itself (see box50k above); PARDISO's refactorisation on 2 cores is "
              "what a user would get, symbolic analysis reused",
    "memory": "per tet: the per-corner buffer of the gather (48 B), Bm and Bm R^T (72 B), the quaternion, last "
              "turn and twist (32 B), the tet's corners and their adjacency slots (32 B), rest volume and body "
              "(8 B); per vertex, 3-vectors of 12 B in f32: the rest shape, the two swapped states, where "
              "the last step ended, the potential's, CG's, Newton's and BDF2's history (20, 240 B a vertex, about 70 B/tet "
              "on epcot); fields sized to a capacity (5 % unused on "
              "epcot); on large meshes the two-level preconditioner's dense coarse inverse (up to 768 x 768: "
              "2.4 MB in f32, 48 B/tet on box50k). 200 B/tet would need Bm R^T recomputed in every CG "
              "product or the gather's buffer replaced by atomics: both slower, and atomics would add in a "
              "different order on every run, where runs are now reproducible bit for bit",
}


def targets(results):
    """The speed targets (issue 12) with what this run measured, met or not, and what limits each
    (a quick run measures none of them)."""
    if is_quick(results):
        return ["## Targets", "",
                f"Not measured in a quick run: the speed targets are set on {TARGET_SCENE}, epcot, the stiff bar, "
                "the pile and the start-up, which only the full run (`bench`) measures; docs/benchmark.md has "
                "them.", ""]
    by_name = {s["name"]: s for s in results["scenes"]}
    rows = []

    def add(target, goal, value, unit, met, limit):
        text = "–" if value is None else f"{value:.3g} {unit}"
        verdict = "not measured" if value is None else "reported" if met is None else "met" if met(value) else "not met"
        rows.append(f"| {target} | {goal} | {text} | {verdict} | {LIMITS.get(limit, '') if verdict == 'not met' else ''} |")

    start = results.get("startup", {})
    add("start-up, warm cache", "<= 2 s", start.get("warm_s"), "s", lambda v: v <= 2, "warm")
    if start.get("taichi_s"):
        add(f"start-up, warm cache, over Taichi's own start ({start['taichi_s']:.2f} s)", "<= 2 x",
            start["warm_s"] / start["taichi_s"], "x", lambda v: v <= 2, "warm")
    add("start-up, cold cache", "(reported)", start.get("cold_s"), "s", None, "")
    add("second Simulation, same kind, to its first step", "<= 0.3 s", start.get("second_s"), "s",
        lambda v: v <= 0.3, "")
    add("second Simulation beside a live one", "(reported)", start.get("beside_s"), "s", None, "")
    add("`view`, first frame (the scene at rest), warm cache", "<= 3 s", start.get("view_first_s"), "s",
        lambda v: v <= 3, "")
    add("`view`, first stepped frame, warm cache", "(reported)", start.get("view_stepped_s"), "s", None, "")
    box = by_name.get(TARGET_SCENE)
    row = box and find(box, method="corotational", solver="pcg", step="single", dt_factor=1, tolerance=1e-3)
    if row:
        add("rotation extraction, box50k", "<= 15 ns/tet", 1e6 * row["rotation_ms"] / box["tets"], "ns/tet",
            lambda v: v <= 15, "rotation")
        add("box50k corotational, PCG 1e-3, one-solve step", ">= 60 steps/s", 1e3 / row["ms_median"], "steps/s",
            lambda v: v >= 60, "box50k")
        newton = find(box, method="corotational", solver="pcg", step="newton", dt_factor=1, tolerance=1e-3,
                      integrator="bdf2")                              # the row its "what limits it" describes
        add("box50k corotational, PCG 1e-3, Newton step", ">= 60 steps/s", newton and 1e3 / newton["ms_median"],
            "steps/s", lambda v: v >= 60, "newton")
    shares = [100 * r["rotation_ms"] / r["ms_median"] for s in results["scenes"]
              if (r := find(s, method="corotational", solver="pcg", step="single", dt_factor=1, tolerance=1e-3))]
    add("corotation's fixed work, one-solve step at PCG 1e-3, worst scene", "<= 5 %", max(shares, default=None),
        "%", lambda v: v <= 5, "fixed")
    stiff = results.get("stiff")
    if stiff:
        chosen = stiff["preconditioners"][stiff["preconditioners"]["auto"]]
        add(f"stiff bar ({stiff['name']}, E {stiff['E']:g} Pa, nu {stiff['nu']:g}) corotational, PCG 1e-3, "
            "one-solve step", ">= 30 steps/s", chosen["steps_per_s"], "steps/s", lambda v: v >= 30, "stiff")
    resting = start.get("resting_ms")
    add("a scene whose bodies all rest (epcot), share of an awake step", "<= 5 %",
        resting and 100 * resting[0] / resting[1], "%", lambda v: v <= 5, "")
    if box and any(r["solver"] == "direct" for r in box["variants"]):
        ratio = direct_comparison(box)[1]
        fastest = next(r for r in box["variants"] if r["solver"] == "direct")["backend"]
        add(f"direct baseline ({fastest}) over the matrix-free step, box50k", ">= 30 x", ratio[fastest], "x",
            lambda v: v >= 30, "direct")
    contact = results.get("contact")
    add("contact's own kernels, share of the pile's step (20 bodies)", "<= 30 %",
        contact and 100 * contact["on"]["share"], "%", lambda v: v <= 30, "")
    epcot = by_name.get("epcot")
    row = epcot and baseline(epcot, "corotational", "newton")
    add("memory, epcot, model + state + solver", "<= 200 B/tet", row and row["bytes_per_tet"], "B/tet",
        lambda v: v <= 200, "memory")
    return ["## Targets", "",
            "Measured in this run (start-up: `app/bench/startup.py`, medians of 3; the window on $DISPLAY or, "
            "without one, a virtual display, Xvfb). No GPU was available.", "",
            "| target | goal | measured | verdict | what limits it |", "|---|---|---:|---|---|", *rows, ""]


def startup_table(results):
    """Where a warm start of `simulate SCENE --steps 1` goes, per scene and switch, and its slowest
    kernels (app/bench/startup_probe.py); [] when the run did not measure it."""
    starts = results.get("startup", {}).get("breakdown")
    if not starts:
        return []
    when = (f", {starts[0]['date']}, load average {max(row['load_average'] for row in starts):.1f} or less"
            if "date" in starts[0] else "")
    lines = ["## Where a warm start goes", "",
             "`main.py simulate SCENE --steps 1` in a new process, Taichi's offline cache filled (medians of 3, "
             f"seconds; `app/bench/startup_probe.py`{when}). *imports*: Python's, Taichi's among them; *Taichi*: "
             "`ti.init`; *build*: the scene read, the model and solver made; *first step* holds the kernels' "
             "*translate* (Taichi turning each kernel's Python into its IR, on every start) and *compile* (the "
             "first launch: Taichi 1.7's CPU cache keeps LLVM IR, so LLVM makes machine code again); "
             "*kernels* / *variants*: kernels compiled, and with each set of template arguments counted.", "",
             "| start | total | imports | Taichi | build | first step | translate | compile | kernels | variants |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in starts:
        name = " ".join([Path(row["scene"]).stem, *row["options"]])
        lines.append(f"| {name} | {row['total_s']:.2f} | {row['imports_s']:.2f} | {row['init_s']:.2f} "
                     f"| {row['build_s']:.2f} | {row['first_step_s']:.2f} | {row['translate_s']:.2f} "
                     f"| {row['compile_s']:.2f} | {row['kernels']:.0f} | {row['variants']:.0f} |")
    first = next((row for row in starts if row["scene"] == "epcot" and not row["options"]), starts[0])
    lines += ["", f"The slowest kernels of {Path(first['scene']).stem}'s start (translate + compile, s):", "",
              "| kernel | translate | compile | variants |", "|---|---:|---:|---:|"]
    lines += [f"| {k['kernel']} | {k['translate_s']:.2f} | {k['compile_s']:.2f} | {k['variants']} |"
              for k in first["slowest"]]
    return lines + [""]


def integrator_table(scenes):
    """Per scene: the reference's floor and each integrator's observed order; then each second-order
    integrator against backward Euler."""
    lines = ["", "## Integrators and the reference's floor", "",
             f"Corotational, PCG {sci(BASELINE_TOLERANCE)}. *its order*: the reference's own, from its runs at 2 and "
             "4 dt_ref; *floor*: the reference's own error, its distance to the run at 2 dt_ref over 2^p - 1; "
             "*order*: the slope of log error against log dt over the dt axis (–: fewer than two errors above "
             f"{ORDER_MARGIN} times the floor).", "",
             "| scene | dt_ref (s) | distance at 2 dt_ref | its order | floor | "
             + " | ".join(f"order, {INTEGRATORS[i]} Newton | single" for i in INTEGRATORS) + " |",
             "|---|---:|---:|---:|---:|" + "---:|" * (2 * len(INTEGRATORS))]
    for s in scenes:
        order = s["observed_order"]
        cells = [fmt(order.get(i, {}).get(step), ".2f") for i in INTEGRATORS for step in ("newton", "single")]
        lines.append(f"| {s['name']} | {s['reference_dt']:g} | {s['reference_difference']:.1e} "
                     f"| {s['reference_order']:.2f} | {s['reference_floor']:.1e} | " + " | ".join(cells) + " |")
    lines += ["", "### Second order against backward Euler", "",
              "Each second-order integrator's error and time per simulated second over backward Euler's, at the "
              "scene's dt, and the largest dt of its dt axis whose error plus the floor is within the goal.", "",
              "| scene | integrator | error / BE, Newton | single | s/sim s / BE, Newton | single "
              "| largest dt within goal, Newton | single |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]
    for s in scenes:
        for integrator in SECOND_ORDER:
            pairs = [(baseline(s, "corotational", step, integrator=integrator), baseline(s, "corotational", step))
                     for step in ("newton", "single")]
            if any(a is None for a, _ in pairs):       # results from before this integrator was measured
                continue
            cells = [fmt(ratio(final_error(a), final_error(b)), ".2g") for a, b in pairs]
            cells += [fmt(ratio(a["s_per_sim_s"], b["s_per_sim_s"]), ".2f") for a, b in pairs]
            cells += [fmt(goal_dt(s, step, integrator), "g", "none") for step in ("newton", "single")]
            lines.append(f"| {s['name']} | {INTEGRATORS[integrator]} | " + " | ".join(cells) + " |")
    return lines


def ratio(a, b):
    return a / b if a is not None and b else None


def preconditioner_table(results):
    """Block Jacobi against two-level PCG per scene, and what "auto" picks."""
    rows = [(s["name"], s["vertices"], s["preconditioners"]) for s in results["scenes"] if "preconditioners" in s]
    if "stiff" in results:
        stiff = results["stiff"]
        rows.append((f"{stiff['name']}, E {stiff['E']:g} Pa, nu {stiff['nu']:g}",
                     next((s["vertices"] for s in results["scenes"] if s["name"] == stiff["name"]), None),
                     stiff["preconditioners"]))
    if not rows:
        return []
    lines = ["## Preconditioners", "",
             f"Corotational, one-solve step, PCG {sci(PRECONDITIONER_TOLERANCE)}, the scene's dt; the two "
             "preconditioners stepped in turn (two Simulations), so both see the same machine load. *ratio*: "
             "two-level ms over block Jacobi ms. The default, \"auto\", takes the two-level one from "
             f"{TWO_LEVEL_VERTICES} vertices up.", "",
             "| scene | vertices | block Jacobi ms/step | iters | two-level ms/step | iters | ratio | auto picks |",
             "|---|---:|---:|---:|---:|---:|---:|---|"]
    for name, vertices, p in rows:
        jacobi, two = p["jacobi"], p["two-level"]
        lines.append(f"| {name} | {fmt(vertices, 'd')} | {jacobi['ms_median']:.3g} | {jacobi['iters_per_step']:.3g} "
                     f"| {two['ms_median']:.3g} | {two['iters_per_step']:.3g} "
                     f"| {two['ms_median'] / jacobi['ms_median']:.2f} | {p['auto']} |")
    return lines + [""]


def kernel_profile(results):
    """Where the steps of the profiled box go, kernel by kernel (`simulate --profile`'s table)."""
    if "profile" not in results:
        return []
    p = results["profile"]
    lines = ["## Where a step's time goes", "",
             f"{p['scene']} ({p['tets']} tets), Taichi's kernel profiler (`simulate --profile`, app/profile.py), "
             f"{p['machine']}: {p['steps']} steps of each kind after {p['warmup']} from the start. *tasks*: the "
             "device launches (a task per top-level loop of a kernel); *share*: of the profiled steps' wall time, "
             "added up (so the shares add up to at most 100 %), whose time outside kernels is Python, launching "
             "and waiting. Bytes need CUDA's CUPTI counters: n/a on a CPU. "
             "On a GPU, `python -m tools.gpu_measure OUT.md --arch gpu` times box bars of 49k to 2M tets and "
             "prints these tables for 49k and 973k: docs/gpu.md has them for an NVIDIA H100 80GB HBM3 (and an "
             "H200's bytes), with the bytes each kernel moves as Nsight Compute counts them (`tools/gpu_bytes.py`).",
             ""]
    for kind, table in p["kinds"].items():
        # results from before the steps' summed wall time was kept (docs/benchmark.json): the median's multiple
        wall_ms = table.get("wall_ms", table["steps"] * table["ms_median"])
        lines += [f"**{kind} step**, {table['ms_median']:.3g} ms/step median with the profiler on:", "",
                  profile.markdown(table["rows"], table["steps"], wall_ms, top=15), "",
                  f"Launches: {profile.launches_note(table)}.", ""]
    return lines


def contact_cost(results):
    """A scene's steps with contact and with it off (`main.py bench`'s contact scene: the pile)."""
    if "contact" not in results:
        return []
    c = results["contact"]
    on, off = c["on"], c["off"]
    kernels = ", ".join(f"`{name}` {100 * share:.1f} %" for name, share in
                        sorted(on["kernels"].items(), key=lambda item: -item[1]) if share >= 0.001)
    return ["## What contact costs", "",
            f"{c['scene']} ({c['bodies']} bodies, {c['vertices']} vertices), {c['machine']}: {c['steps']} steps after "
            f"{c['warmup']} from the start, with contact between bodies and with it off (the bodies then pass "
            "through each other), Taichi's profiler on (read the ratio, not the times).", "",
            "| contact | ms/step | Newton it./step | CG it./step | steps not converged | pairs touching |",
            "|---|---:|---:|---:|---:|---:|",
            f"| on | {on['ms_median']:.3g} | {on['newton']:.1f} | {on['cg']:.0f} | {on['unconverged']} of "
            f"{c['steps']} | {on['pairs']:.0f} |",
            f"| off | {off['ms_median']:.3g} | {off['newton']:.1f} | {off['cg']:.0f} | {off['unconverged']} of "
            f"{c['steps']} | – |", "",
            f"Contact's own kernels (broad phase, step bound, first iterate, lagged friction, stats) take "
            f"{100 * on['share']:.1f} % of the step ({kernels}). The rest of what it costs, "
            f"{on['ms_median'] / off['ms_median']:.1f} times the step without it, is the Newton and CG iterations "
            "the pairs add (docs/method.md, section 6).", ""]


def direct_split(scene):
    """Where a direct step's time goes, per solver and method."""
    parts = []
    for r in scene["variants"]:
        if r["solver"] == "direct":
            once = "" if r["backend"] == "superlu" else f" (and once, the pattern's analysis: {r['analysis_ms']:.3g})"
            parts.append(f"{r['name']}: rotations {r['rotation_ms']:.3g}, assembly {r['assembly_ms']:.3g}, "
                         f"factorisation {r['factorise_ms']:.3g}, forces and solve {r['solve_ms']:.3g}{once}")
    return "Direct steps, ms (medians): " + "; ".join(parts) + "."


def write(results, out=DOCS, names=RESULT_FILES):
    with atomic_open(Path(out) / names["json"]) as f:
        json.dump(results, f, indent=1)
    with atomic_open(Path(out) / names["md"]) as f:
        f.write(markdown(results))
    if "plot" in names:                       # a refresh of one section leaves the plot as it was
        with atomic_open(Path(out) / names["plot"], "wb") as f:
            plot(results, f)
    if "numbers" in names:
        with atomic_open(Path(out) / names["numbers"]) as f:
            json.dump(numbers(results, Path(out) / names["json"]), f, indent=1)
