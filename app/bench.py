"""`main.py bench`: what accuracy costs in time.

Every scene first runs a reference: corotational backward Euler at a small time step
(dt_ref = the scene's dt / 8, 0.0025 s for the seed scenes), Newton iterated to 1e-10
with PCG at 1e-10 and SVD rotations, always in float64. Then every variant runs from
the same start for the same simulated time:

    corotational, Newton step and one-solve ("single") step, each with
        PCG 1e-4 at dt = 2, 1, 1/2, 1/4 x the scene's dt     (the dt axis)
        PCG 1e-2, 1e-3, 1e-6 at the scene's dt               (the tolerance axis)
    linear: the same, once (one Newton iteration solves a linear body exactly)
    both methods, one-solve step at the scene's dt:
        Jacobi iteration at 10, 30, 100 iterations           (matrix-free, fem.solver)
        direct sparse solvers                                (assembled and factorised, app.direct):
            the fastest installed (MKL PARDISO with the fast-direct extra), its analysis of the
            pattern made once and the matrix refactorised every step, and SuperLU, from
            scratch every step (the coursework's way)

A variant's error is its RMS position distance to the reference at checkpoint times
that every dt divides. The reference has an error of its own, O(dt_ref) like any
backward Euler run: the distance between it and a second run at 2 dt_ref estimates
it (for a first-order method the two differ by about the reference's own error). That
floor is where the error axis bottoms out; errors near it are measured too low (a variant
at dt shows about (dt - dt_ref) / dt of its true error, half of it at dt = 2 dt_ref), so a
variant meets the error goal only when its error plus the floor does. dt_ref = the
smallest variant dt / 8 would lower the floor 4 times, but the reference, already the
dearest run of a scene, would cost 4 times more: the scene's dt / 8 keeps a full run
affordable.

A variant's cost is the wall time of a step, measured after warm-up (Taichi compiles
its kernels on first use), and the wall time per simulated second (ms per step / dt),
which compares runs at different dt.
Outputs: results.md (tables), results.json (every number), accuracy_vs_time.png; with --docs,
the pages in docs/ instead: benchmark.md, benchmark.json (from which `main.py figures` redraws
the plot) and accuracy_vs_time.png.
"""

import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import taichi as ti

import fem
import scenes
from app import device, direct, outputs, startup
from app.files import atomic_open, check_output, refuse_overwrite
from app.progress import Progress
from assets.generators import box
from fem.errors import FemError
from fem.solver import TWO_LEVEL_VERTICES
from fem.scene import Body, Effects, Initial, Material, Scene, Selection, SolverSettings, place_mesh

DT_FACTORS = (2, 1, 0.5, 0.25)   # the dt axis, times the scene's dt (0.04 to 0.005 s for the seed scenes)
PCG_TOLERANCES = (1e-2, 1e-3, 1e-4, 1e-6)
JACOBI_ITERATIONS = (10, 30, 100)
BASELINE_TOLERANCE = 1e-4        # the scenes' default PCG tolerance: the dt axis and the comparisons use it
DIRECT_TOLERANCE = 1e-3          # the matrix-free step set against the direct baseline: as accurate as an
                                 # exact solve of the same step (the 1e-3 and 1e-6 rows' errors agree)
DIRECT_TARGET = 30               # issue 12: the matrix-free step at least 30 times faster than the fastest direct one
MAX_ITERATIONS = 1000            # PCG: the tolerance, not the cap, ends a solve
REFERENCE_REFINEMENT = 8         # dt_ref = the scene's dt / 8
REFERENCE_SETTINGS = dict(step="newton", method="pcg", tolerance=1e-10, newton_tolerance=1e-10,
                          max_newton=50, rotations="svd")
ERROR_GOAL = 1e-2                # accurate enough: RMS position error under 1 % of the bounding-box diagonal
                                 # (against a converged reference backward Euler's own error dominates, and
                                 # 0.1 % lies below the reference's floor on the spinning bars)
MIN_TIMED_STEPS = 3              # a variant stopped by the time budget still times this many steps
BOXES = {"box80": 2, "box1k": 5, "box10k": 10, "box50k": 17}   # 2 x 1 x 1 m bar, 2k x k x k cells
# What `write` names its files: in --out, and as the committed pages in docs/ (`bench --docs`).
RESULT_FILES = {"json": "results.json", "md": "results.md", "plot": "accuracy_vs_time.png"}
DOCS = Path(__file__).resolve().parents[1] / "docs"
DOCS_FILES = {"json": "benchmark.json", "md": "benchmark.md", "plot": "accuracy_vs_time.png"}


@dataclass
class Plan:
    """How much to measure."""

    scenes: list          # built-in names, scene files or BOXES names
    checkpoints: tuple    # s: positions are compared with the reference at these times (rounded to a
                          # multiple of the largest dt); the last ends a run
    warmup_steps: int     # first steps of every run left out of the timings
    budget_s: float       # a variant whose run would take longer stops early (the reference never does)
    startup: str = ""     # a scene whose start-up and resting cost are measured too ("": none)
    stiff: str = ""       # a BOXES bar also compared, made STIFF, on preconditioners alone ("": none)
    preconditioner_steps: int = 30   # steps of each preconditioner in their comparison


def full_plan():
    return Plan([*scenes.builtin_scenes(), "box1k", "box10k", "box50k"], (0.4, 1.0, 2.0), 2, 120.0, "epcot",
                "box50k")


QUICK = Plan(["cube86", "box1k"], (0.4, 1.0), 2, 20.0)
TEST = Plan(["box80"], (0.08, 0.2), 2, 10.0, stiff="box80", preconditioner_steps=3)   # tests: seconds


@dataclass(frozen=True)
class Variant:
    method: str               # "linear" | "corotational"
    solver: str               # "reference" | "pcg" | "jacobi" | "direct"
    step: str = "single"      # "newton" | "single"; a linear body takes the same step either way
    dt_factor: float = 1      # its dt: this times the scene's dt
    tolerance: float = 0.0    # pcg, reference
    iterations: int = 0       # jacobi
    backend: str = ""         # direct: a name in app.direct.BACKENDS

    @property
    def name(self):
        """What it solves with, e.g. "corotational PCG 1e-4"."""
        if self.solver == "reference":
            return "reference" if self.dt_factor == 1 / REFERENCE_REFINEMENT else "reference at 2 dt_ref"
        if self.solver == "direct":
            return f"{self.method} direct ({direct_role(self.backend)})"
        setting = {"pcg": f"PCG {sci(self.tolerance)}", "jacobi": f"Jacobi x{self.iterations}"}[self.solver]
        return f"{self.method} {setting}"

    def dt(self, scene_dt):
        return self.dt_factor * scene_dt

    @property
    def step_name(self):
        return "exact" if self.method == "linear" else {"newton": "Newton", "single": "single"}[self.step]


REFERENCES = [Variant("corotational", "reference", "newton", k / REFERENCE_REFINEMENT,
                      REFERENCE_SETTINGS["tolerance"]) for k in (1, 2)]   # the reference, and at 2 dt_ref


def direct_backends():
    """The direct baseline: the fastest solver installed, and SuperLU, the coursework's (once if they are one)."""
    return list(dict.fromkeys([direct.fastest_available(), "superlu"]))


def direct_role(backend):
    """'fastest: MKL PARDISO' or 'SuperLU, coursework-like'."""
    return "SuperLU, coursework-like" if backend == "superlu" else f"fastest: {direct.BACKENDS[backend].label}"


def variants():
    """Every variant but the references, in the order of the tables."""
    out = []
    for method, steps in (("corotational", ("newton", "single")), ("linear", ("newton",))):
        for step in steps:
            out += [Variant(method, "pcg", step, f, BASELINE_TOLERANCE) for f in DT_FACTORS]
            out += [Variant(method, "pcg", step, 1, tol) for tol in PCG_TOLERANCES if tol != BASELINE_TOLERANCE]
        out += [Variant(method, "jacobi", iterations=k) for k in JACOBI_ITERATIONS]
        out += [Variant(method, "direct", backend=name) for name in direct_backends()]
    return out


def sci(x):
    """1e-04 -> 1e-4."""
    return f"{x:.0e}".replace("e-0", "e-").replace("e+0", "e")


# ---------------------------------------------------------------- scenes

def box_scene(name, k):
    """A 2 x 1 x 1 m rubber bar of 2k x k x k cells (10 k^3 tets), spinning about y at 2 rad/s and
    twisting about its long axis: it turns by 4 rad in 2 s, so linear FEM visibly fails."""
    mesh = place_mesh(box((2.0, 1.0, 1.0), (2 * k, k, k)))
    scene = Scene(name, [Body("bar", mesh, Material(E=1e5, nu=0.3, density=1000.0))],
                  description="A 2 x 1 x 1 m rubber bar spinning about y and twisting about its long axis.",
                  effects=Effects(beta=0.002), solver=SolverSettings(dt=0.02))
    scene.initial = [Initial(Selection(None), "spin", (np.array([0.0, 1.0, 0.0]), 2.0)),
                     Initial(Selection(None), "twist", (np.array([1.0, 0.0, 0.0]), 6.0))]
    return scene


def make_scene(ref):
    return box_scene(ref, BOXES[ref]) if ref in BOXES else scenes.load_scene(ref)


def checkpoint_times(plan, dt):
    """The plan's checkpoints rounded to multiples of the largest dt, so that every dt divides them."""
    period = max(DT_FACTORS) * dt
    return [period * max(1, round(t / period)) for t in plan.checkpoints]


# ---------------------------------------------------------------- running

def field_bytes(*objects):
    """Bytes held by the Taichi fields that are attributes of `objects`."""
    return sum(f.to_numpy().nbytes for o in objects for f in vars(o).values() if isinstance(f, ti.Field))


def configure(sim, variant):
    """Set the engine up for a variant and go back to t = 0."""
    settings = replace(sim.scene.solver, dt=variant.dt(sim.scene.solver.dt), step=variant.step,
                       method="pcg", max_iterations=MAX_ITERATIONS)
    if variant.solver == "reference":
        settings = replace(settings, **REFERENCE_SETTINGS)
    elif variant.solver == "pcg":
        settings = replace(settings, tolerance=variant.tolerance)
    elif variant.solver == "jacobi":   # a tolerance never reached: exactly `iterations` per step
        settings = replace(settings, method="jacobi", tolerance=1e-12, max_iterations=variant.iterations)
    else:                              # direct: the engine only measures; app.direct reads dt from it
        settings = replace(settings, tolerance=BASELINE_TOLERANCE)
    settings.check(sim.scene.name)
    sim.settings = settings
    sim.set_method(variant.method)
    sim.reset()


def warm_up(sim, steps=2):
    """Compile every kernel the variants use, and the measurements, before anything is timed."""
    engine = [v for v in variants() if v.solver != "direct"]
    for variant in {(v.method, v.solver, v.step): v for v in engine}.values():
        configure(sim, variant)
        for _ in range(steps):
            sim.step()
    sim.stats()


def run_variant(sim, variant, times, plan):
    """Step one variant from t = 0 to the last checkpoint; returns per-step infos, {time: positions}
    at the checkpoints, the volume and energy drift, the memory its solver holds (bytes) and
    whether it stopped early."""
    configure(sim, variant)
    dt = sim.settings.dt
    checkpoint_steps = {round(t / dt): f"{t:g}" for t in times}
    n_steps = max(*checkpoint_steps, plan.warmup_steps + MIN_TIMED_STEPS)
    if variant.solver == "direct":
        solver = direct.DirectSolver(sim, variant.backend)
        step = solver.step

        def observe():
            sim.set_state(solver.x, solver.v)   # the engine measures the direct solver's state too
            return solver.x, sim.stats()
    else:
        step = sim.step

        def observe():
            return sim.positions(), sim.stats()

    energy0 = sum_energy(observe()[1])
    infos, snapshots, volume_drift = [], {}, 0.0
    start = time.perf_counter()
    for k in range(1, n_steps + 1):
        infos.append(step())
        x, stats = observe()
        volume_drift = max(volume_drift, max(abs(r - 1) for r in stats["volume_ratio"]))
        if k in checkpoint_steps:
            snapshots[checkpoint_steps[k]] = x
        may_stop = variant.solver != "reference" and k >= plan.warmup_steps + MIN_TIMED_STEPS
        if may_stop and (time.perf_counter() - start) * n_steps / k > plan.budget_s:   # would take too long
            break
    energy = sum_energy(stats)
    memory = (solver.memory_bytes if variant.solver == "direct" else
              field_bytes(sim.model, sim.state, sim.solver, *filter(None, [sim.solver.patches])))
    return {"infos": infos, "snapshots": snapshots, "run_s": time.perf_counter() - start,
            "volume_drift": volume_drift, "energy_drift": energy / energy0 - 1 if energy0 > 0 else None,
            "memory_bytes": memory, "stopped_early": len(infos) < n_steps,
            "analysis_ms": solver.analysis_ms if variant.solver == "direct" else None}


def sum_energy(stats):
    return stats["kinetic_energy"] + stats["elastic_energy"]


def summarise(variant, run, reference, sim, times, plan):
    """One table row: timings after warm-up, iterations, memory and errors against the reference."""
    infos = run["infos"]
    timed = infos[plan.warmup_steps:]
    ms = [i["wall_ms"] for i in timed]
    dt = variant.dt(sim.scene.solver.dt)
    X = sim.model.rest_positions_np
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    errors = {}
    for t in map("{:g}".format, times):
        x = run["snapshots"].get(t)
        errors[t] = None if x is None else rms(x - reference[t]) / diagonal
    row = {
        "label": f"{variant.name} ({variant.step_name}, dt {dt:g} s)", "name": variant.name,
        "method": variant.method, "solver": variant.solver, "step": variant.step, "dt": dt,
        "dt_factor": variant.dt_factor, "tolerance": variant.tolerance or None,
        "iterations": variant.iterations or None,
        "steps": len(infos), "timed_steps": len(timed), "stopped_early": run["stopped_early"],
        "run_s": run["run_s"], "first_step_ms": infos[0]["wall_ms"],
        "ms_median": statistics.median(ms), "ms_min": min(ms), "ms_max": max(ms),
        "s_per_sim_s": statistics.median(ms) / dt / 1000,
        "rotation_ms": statistics.median(i["rotation_ms"] for i in timed),
        "bytes_per_tet": run["memory_bytes"] / sim.model.n_tets,
        "errors": errors, "volume_drift": run["volume_drift"], "energy_drift": run["energy_drift"],
    }
    if variant.solver == "direct":   # the analysis, once before the first step, is in no step's time
        row.update(backend=variant.backend, analysis_ms=run["analysis_ms"],
                   **{k: statistics.median(i[k] for i in timed) for k in ("assembly_ms", "factorise_ms", "solve_ms")})
    else:
        per_iter = statistics.median(i["solve_ms"] / max(i["solver_iters"], 1) for i in timed)
        row.update(newton_per_step=statistics.mean(i["newton_iters"] for i in infos),
                   iters_per_step=statistics.mean(i["solver_iters"] for i in infos),
                   line_search_steps=sum(i["line_search_steps"] for i in infos),
                   energy_limited=sum(i["energy_limited"] for i in infos),
                   ms_per_iter=per_iter, ns_per_tet_iter=1e6 * per_iter / sim.model.n_tets,
                   converged=sum(i["converged"] for i in infos) / len(infos))
    return row


def rms(d):
    return float(np.sqrt((d ** 2).sum(axis=1).mean()))


def measure_references(scene, times, plan, args, progress):
    """Rows of the reference and its twin at 2 dt_ref, and the reference's {time: positions}.

    They run in f64: a bench in f32 restarts Taichi in f64 and back (which ends every
    Simulation made before; the positions are numpy arrays and outlive it)."""
    if args.precision != "f64":
        fem.init(args.arch, "f64", debug=args.debug)
    sim = fem.Simulation(scene)
    rows, reference = [], None
    for variant in REFERENCES:
        progress.set_description(f"{scene.name}: {variant.name}")
        run = run_variant(sim, variant, times, plan)
        if reference is None:
            reference = run["snapshots"]
        rows.append(summarise(variant, run, reference, sim, times, plan))
        progress.update()
    if args.precision != "f64":
        fem.init(args.arch, args.precision, debug=args.debug)
    return rows, reference


PRECONDITIONER_TOLERANCE = 1e-3   # the comparison of preconditioners: corotational, one-solve step, this PCG tolerance
STIFF = dict(E=1e6, nu=0.4)       # the stiff bar: box50k ten times stiffer and nearer incompressible


def compare_preconditioners(scene, steps):
    """Block Jacobi against two-level PCG on one scene (corotational, one-solve step, PCG 1e-3):
    two Simulations stepped in turn, so that both see the same machine noise. Returns
    {"jacobi": row, "two-level": row, "auto": what "auto" picks}, a row holding ms_median,
    iters_per_step and steps_per_s over `steps` steps after two warm-up steps."""
    out, sims = {}, {}
    for name in ("jacobi", "two-level"):
        settings = replace(scene.solver, step="single", method="pcg", tolerance=PRECONDITIONER_TOLERANCE,
                           preconditioner=name, max_iterations=MAX_ITERATIONS)
        sims[name] = fem.Simulation(replace(scene, solver=settings))
        sims[name].set_method("corotational")
        for _ in range(2):
            sims[name].step()
    infos = {name: [] for name in sims}
    for _ in range(steps):
        for name, sim in sims.items():
            infos[name].append(sim.step())
    for name, rows in infos.items():
        ms = statistics.median(i["wall_ms"] for i in rows)
        out[name] = {"ms_median": ms, "steps_per_s": 1e3 / ms,
                     "iters_per_step": statistics.mean(i["solver_iters"] for i in rows)}
    auto = sims["jacobi"]
    auto.settings = replace(auto.settings, preconditioner="auto")
    out["auto"] = auto.solver.preconditioner
    return out


def stiff_bar(ref):
    """The BOXES bar `ref` with the STIFF material."""
    scene = make_scene(ref)
    body = scene.bodies[0]
    scene.bodies[0] = replace(body, material=replace(body.material, **STIFF))
    scene.name, scene.description = f"{ref}, stiff", f"{scene.description} E {STIFF['E']:g} Pa, nu {STIFF['nu']:g}."
    return scene


def measure_scene(ref, plan, args, progress):
    scene = make_scene(ref)
    times = checkpoint_times(plan, scene.solver.dt)
    rows, reference = measure_references(scene, times, plan, args, progress)
    sim = fem.Simulation(scene)
    progress.set_description(f"{ref}: compiling")
    warm_up(sim)
    for variant in variants():
        progress.set_description(f"{ref}: {variant.name}")
        run = run_variant(sim, variant, times, plan)
        rows.append(summarise(variant, run, reference, sim, times, plan))
        progress.update()
    progress.set_description(f"{ref}: preconditioners")
    preconditioners = compare_preconditioners(scene, plan.preconditioner_steps)
    return {"name": ref, "description": scene.description, "tets": sim.model.n_tets,
            "vertices": sim.model.n_vertices, "dt": scene.solver.dt, "reference_dt": rows[0]["dt"],
            "reference_floor": final_error(rows[1]), "checkpoints": times, "variants": rows,
            "preconditioners": preconditioners}


# ---------------------------------------------------------------- conclusions

def find(scene, **fields):
    """The first row whose fields have these values, or None."""
    return next((r for r in scene["variants"] if all(r[k] == v for k, v in fields.items())), None)


def final_error(row):
    return list(row["errors"].values())[-1]


def baseline(scene, method, step, solver="pcg"):
    """The row at the scene's dt with the default tolerance (PCG), or the solver alone (direct: the fastest)."""
    if solver != "pcg":
        return find(scene, method=method, solver=solver)
    return find(scene, method=method, solver="pcg", step=step, dt_factor=1, tolerance=BASELINE_TOLERANCE)


def corotation_cost(scene, step, solver="pcg"):
    """Extra time per step of corotational over linear FEM, in %."""
    corot, linear = baseline(scene, "corotational", step, solver), baseline(scene, "linear", "newton", solver)
    return 100 * (corot["ms_median"] / linear["ms_median"] - 1)


def meets_goal(row, scene):
    """Error plus the reference's own error (so a bound on the true error) within the goal."""
    error = final_error(row)
    return error is not None and error + scene["reference_floor"] <= ERROR_GOAL


def goal_dt(scene, step):
    """The largest dt of the corotational dt axis (PCG at the default tolerance) that meets the goal."""
    rows = [find(scene, method="corotational", solver="pcg", step=step, dt_factor=f, tolerance=BASELINE_TOLERANCE)
            for f in DT_FACTORS]
    return next((r["dt"] for r in rows if meets_goal(r, scene)), None)


def cheapest_to_goal(scene, step):
    """The corotational PCG row of this step kind that meets the goal in the least time per simulated second."""
    rows = [r for r in scene["variants"] if r["method"] == "corotational" and r["solver"] == "pcg"
            and r["step"] == step and meets_goal(r, scene)]
    return min(rows, key=lambda r: r["s_per_sim_s"], default=None)


def frontier(scene):
    """Variants no other variant beats in both time per simulated second and accuracy (at the last checkpoint)."""
    rows = [r for r in scene["variants"] if r["solver"] != "reference" and final_error(r) is not None]
    return [r["label"] for r in sorted(rows, key=lambda r: r["s_per_sim_s"])
            if not any(o["s_per_sim_s"] < r["s_per_sim_s"] and final_error(o) <= final_error(r) for o in rows)]


def direct_comparison(scene):
    """The matrix-free corotational one-solve step at PCG 1e-3 (at the baseline tolerance when the tolerance
    axis lacks 1e-3) against the direct baseline: a sentence, and {solver: direct ms per step / matrix-free ms
    per step} with "factorisation" (the fastest's alone)."""
    tolerance = DIRECT_TOLERANCE if DIRECT_TOLERANCE in PCG_TOLERANCES else BASELINE_TOLERANCE
    matrix_free = find(scene, method="corotational", solver="pcg", step="single", dt_factor=1, tolerance=tolerance)
    rows = [r for r in scene["variants"] if r["method"] == "corotational" and r["solver"] == "direct"]
    ms = matrix_free["ms_median"]
    ratios = {r["backend"]: r["ms_median"] / ms for r in rows}
    fastest = rows[0]
    ratios["factorisation"] = fastest["factorise_ms"] / ms
    role = "the fastest direct solver installed" if fastest["backend"] != "superlu" else "the direct solver"
    sentence = (f"On {scene['name']} ({scene['tets']} tets) the matrix-free corotational one-solve step at PCG "
                f"{sci(tolerance)} takes {ms:.3g} ms; {role}, {direct.BACKENDS[fastest['backend']].label} "
                f"refactorising every step, takes {ratios[fastest['backend']]:.2g} times as long "
                f"({fastest['ms_median']:.3g} ms; its factorisation alone {fastest['factorise_ms']:.3g} ms, "
                f"{ratios['factorisation']:.2g} times)")
    if len(rows) > 1:
        sentence += f", SuperLU {ratios['superlu']:.2g} times ({rows[1]['ms_median']:.3g} ms)"
    exact = fastest if final_error(fastest) is not None else find(     # a direct run stopped by the budget
        scene, method="corotational", solver="pcg", step="single", dt_factor=1, tolerance=min(PCG_TOLERANCES))
    sentence += (f"; the matrix-free step's position error {final_error(matrix_free):.2e}, the exact solve's "
                 f"{final_error(exact):.2e}" + ("" if exact is fastest else f" (at PCG {sci(exact['tolerance'])})"))
    met = "met" if ratios[fastest["backend"]] >= DIRECT_TARGET else "not met"
    return sentence + f". Target: at least {DIRECT_TARGET} times, {met}.", ratios


def spread(values, spec=".2f"):
    """'lo to hi' of several values ('' for one)."""
    return f"{min(values):{spec}} to {max(values):{spec}}" if len(values) > 1 else ""


def median_ratio(pairs):
    """(median of a / b, every a / b) over the pairs where both are known and non-zero."""
    ratios = [a / b for a, b in pairs if a and b]
    return (statistics.median(ratios), ratios) if ratios else (None, [])


def where_met(dts):
    """'reaches it at dt 0.04 s in 2 of 4 scenes, 0.01 s in 1, never in 1', from the largest dt meeting
    the goal in each scene (None: none does)."""
    counts = Counter(dts)
    found = sorted((d for d in counts if d is not None), reverse=True)
    if not found:
        return "never reaches it" if len(dts) == 1 else f"reaches it in none of the {len(dts)} scenes"
    if len(dts) == 1:
        return f"reaches it at dt {found[0]:g} s"
    parts = [f"{d:g} s in {counts[d]}" for d in found] + ([f"never in {counts[None]}"] if None in counts else [])
    return f"reaches it at dt {parts[0]} of {len(dts)} scenes" + "".join(f", {p}" for p in parts[1:])


def headline(scenes):
    """The measured answers, as sentences and as numbers."""
    n, last = len(scenes), scenes[0]["checkpoints"][-1]
    dts = sorted({s["dt"] for s in scenes})
    at_dt = f"dt {dts[0]:g} s" if len(dts) == 1 else "each scene's dt"
    newton = [baseline(s, "corotational", "newton") for s in scenes]
    single = [baseline(s, "corotational", "single") for s in scenes]
    time_ratio, times = median_ratio((a["s_per_sim_s"], b["s_per_sim_s"]) for a, b in zip(newton, single))
    error_ratio, errors = median_ratio((final_error(a), final_error(b)) for a, b in zip(newton, single))
    goal = {step: [goal_dt(s, step) for s in scenes] for step in ("newton", "single")}
    cheapest = [(cheapest_to_goal(s, "newton"), cheapest_to_goal(s, "single")) for s in scenes]
    pays, pay_ratios = median_ratio((a["s_per_sim_s"], b["s_per_sim_s"]) for a, b in cheapest if a and b)
    floors = [s["reference_floor"] for s in scenes]
    numbers = {
        "newton_over_single_time": time_ratio, "newton_over_single_error": error_ratio,
        "goal_dt": goal,     # per scene, in order: the largest dt meeting the goal (None: none does)
        "cheapest_to_goal_newton_over_single": pays,
        "corotation_cost_single_pct": statistics.median(corotation_cost(s, "single") for s in scenes),
        "corotation_cost_newton_pct": statistics.median(corotation_cost(s, "newton") for s in scenes),
        "corotation_cost_direct_pct": statistics.median(corotation_cost(s, "single", "direct") for s in scenes),
        "reference_floor": statistics.median(floors),
    }
    over = f"; medians over {n} scenes, {spread(times)} and {spread(errors)} times" if n > 1 else ""
    lines = [f"A correct step costs: Newton takes {fmt(time_ratio, '.2f')} times the wall time per simulated "
             f"second of the one-solve step and leaves {fmt(error_ratio, '.2f')} times its error (corotational, "
             f"PCG {sci(BASELINE_TOLERANCE)}, {at_dt}{over})."]
    sentence = (f"Within the error goal ({100 * ERROR_GOAL:g} % of the scene size at t = {last:g} s, the "
                f"reference's own error counted in), at PCG {sci(BASELINE_TOLERANCE)}: Newton "
                f"{where_met(goal['newton'])}; the one-solve step {where_met(goal['single'])}.")
    if pays is not None:
        both = ("" if n == 1 else f" (median over the {len(pay_ratios)} scenes where both meet it)"
                if len(pay_ratios) > 1 else " (in the one scene where both meet it)")
        sentence += (f" The cheapest corotational run within it takes {pays:.2f} times the wall time per simulated "
                     f"second with Newton as with the one-solve step{both}: "
                     + ("Newton pays." if pays < 1 else "Newton does not pay at this goal."))
    lines.append(sentence)
    largest = max(scenes, key=lambda s: s["tets"])
    sentence, numbers["direct_over_matrix_free"] = direct_comparison(largest)
    lines.append(sentence)
    lines.append(f"Corotation costs {numbers['corotation_cost_single_pct']:.0f} % more per step than linear with "
                 f"the matrix-free one-solve step (PCG {sci(BASELINE_TOLERANCE)}), "
                 f"{numbers['corotation_cost_newton_pct']:.0f} % with Newton and "
                 f"{numbers['corotation_cost_direct_pct']:.0f} % with the fastest direct solver"
                 + (" (medians)." if n > 1 else "."))
    dt_ref = f" = {scenes[0]['reference_dt']:g} s" if len(dts) == 1 else ""
    floor_range = f" (median; {spread(floors, '.1e')})" if n > 1 else ""
    lines.append(f"The reference (Newton to 1e-10 in f64 at dt_ref = dt / {REFERENCE_REFINEMENT}{dt_ref}) "
                 f"differs from a run at 2 dt_ref by {numbers['reference_floor']:.1e}{floor_range}: the error "
                 "axis bottoms out there, and errors near it are measured up to 2 times too low.")
    return lines, numbers


# ---------------------------------------------------------------- the machine

def machine(backend, precision):
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    info = {"cpu": cpu, "cores": os.cpu_count(), "load_average": os.getloadavg()[0],
            "taichi": ".".join(map(str, ti.__version__)), "backend": backend, "precision": precision,
            "direct_solver": ", ".join(f"{direct.BACKENDS[b].label} ({direct.BACKENDS[b].library})"
                                       for b in direct_backends()) + ", float64",
            "python": platform.python_version(),
            "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds")}
    if backend == "cuda":
        try:
            info["gpu"] = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                                         capture_output=True, text=True, timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            pass
    return info


# ---------------------------------------------------------------- writing

def fmt(value, spec=".3g", missing="–"):
    return missing if value is None else format(value, spec)


def explanation(results):
    """Two paragraphs: the reference and what its error floor means; the columns."""
    plan = results["plan"]
    reference = (
        "Each run starts from the same state and runs to the last checkpoint. **The reference** is corotational "
        f"backward Euler at dt_ref = the scene's dt / {REFERENCE_REFINEMENT}: Newton until every body's gradient "
        f"is under 1e-10 of the step's own terms (at most {REFERENCE_SETTINGS['max_newton']} iterations), PCG to "
        "1e-10, SVD rotations, in float64 whatever the variants' precision (so its timings are f64's). Being "
        "backward Euler, it has an O(dt_ref) error of its own: *reference at 2 dt_ref*, the same at twice that "
        "dt, differs from it by about that much, and its error is the floor of the error axis. Errors near the "
        "floor are measured too low (a variant at dt shows about (dt - dt_ref) / dt of its true error: 1/2 at "
        "2 dt_ref, 7/8 at 8 dt_ref), so a run meets the goal of "
        f"{100 * ERROR_GOAL:g} % of the scene size only when its error plus the floor does. dt_ref = the "
        "smallest variant dt / 8 would lower the floor 4 times, but the reference, already the dearest run of a "
        "scene, would cost 4 times more.")
    columns = (
        "*step*: Newton (iterated until the velocity settles to the scene's newton_tolerance) or single (one "
        "linear solve with the rotations of the step's start); a linear body's step is exact either way. "
        "*s/sim s*: wall seconds per simulated second, ms/step / dt / 1000 (compares runs at different dt); "
        f"*ms/step*: wall time per step (median, min-max) after {plan['warmup_steps']} warm-up steps, "
        "Taichi kernels compiled beforehand; *Newton*: Newton iterations per step and *iters*: linear solver "
        "iterations per step (means); *ns/tet/iter*: a step's solve time per iteration and tet; *rot ms*: "
        "rotation extraction per step; *halvings*: line-search step halvings and *E-limited*: bodies whose "
        "energy rise was scaled back, both summed over the run; *B/tet*: memory of the solver's data (Taichi "
        "fields of model, state and solver; for the direct solver the matrix and its factor); *err t*: RMS "
        "vertex distance to the reference at time t, divided by the bounding-box diagonal; *vol*: largest "
        "|volume / rest volume - 1| of any body; *energy*: (kinetic + elastic) energy at the end over its "
        "start value, minus 1. A blank (–) error: the variant would have taken longer than its time budget "
        f"({plan['budget_s']:g} s) and stopped early.")
    return reference + "\n\n" + columns


def markdown(results):
    m, lines = results["machine"], []
    lines += ["# What accuracy costs in time", ""]
    lines += [f"- {line}" for line in results["headline"]]
    lines += ["", f"Machine: {m['cpu']}, {m['cores']} cores (load average {m['load_average']:.1f} at the start)"
              + (f", GPU {m['gpu']}" if m.get("gpu") else "") + f"; Taichi {m['taichi']} on {m['backend']}, "
              f"{m['precision']}; direct solvers {m['direct_solver']}; Python {m['python']}; {m['date']}; "
              f"{m['bench_minutes']:.1f} minutes.", "", explanation(results), ""]
    lines += targets(results)
    lines += preconditioner_table(results)
    lines += ["## Summary", "",
              f"Corotational, PCG {sci(BASELINE_TOLERANCE)}; time in wall seconds per simulated second, errors at "
              "the last checkpoint; the largest dt of the dt axis whose error plus the floor is within the goal.", "",
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
    for s in results["scenes"]:
        times = [f"err {t:g} s" for t in s["checkpoints"]]
        lines += ["", f"## {s['name']}", "",
                  f"{s['description']} {s['tets']} tets, {s['vertices']} vertices, scene dt {s['dt']:g} s, "
                  f"dt_ref {s['reference_dt']:g} s.", "",
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
        lines += ["", "Frontier (no variant is both faster per simulated second and more accurate): "
                  + ", ".join(frontier(s)) + "."]
    lines += ["", "![error against wall time per simulated second](accuracy_vs_time.png)", ""]
    return "\n".join(lines)


# What limits each speed target that a run does not meet (profiles taken on the 2-core machine).
LIMITS = {
    "warm": "a warm start of epcot (profiled): Python's imports 0.3 s, starting Taichi 0.17 s, building the "
            "Simulation 0.3 s, the first Newton step 1.45 s and the summary 0.25 s. Of these about 2 s are "
            "kernels, half in each of two stages that run even when the offline cache has the kernel: "
            "Taichi's frontend translating its Python (the gradient and energy, the rotations, PCG and the "
            "summary's measurements 0.15 to 0.3 s each), and loading it: Taichi 1.7's CPU backend caches "
            "LLVM IR, not machine code, so LLVM optimises and compiles each of the 40 kernels again, about "
            "15 ms for the smallest and 0.14 s for PCG's. 2 s would need far fewer, smaller kernels",
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
    "newton": "2.35 Newton iterations a step at 1e-3, each with its own PCG solve and a line-search trial "
              "with its own rotation extraction, then energy and gradient in one pass (float64 sums). Kernel "
              "profile of a box50k Newton step (about 33 ms): rotations 8.2 ms (three passes), energy and "
              "gradient 8.4, PCG 10 (about 10 iterations), the first products 2.9, the block-Jacobi build 1, "
              "the energy before and after 1.1. Tried: blocks rebuilt only when stale (as the one-solve step "
              "does) need 14.7 -> 22.3 PCG iterations a step on epcot, as the twist term moves with the "
              "stretch; a tighter forcing term (0.03) saves half a Newton iteration on box50k and costs as "
              "much in PCG. Newton buys the promise that energy never rises, not accuracy",
    "stiff": "as box50k: iterations (about 11, from 41 with block Jacobi) and the step's fixed work",
    "direct": "the matrix-free step itself (see box50k above); PARDISO's refactorisation on 2 cores is "
              "what a user would get, symbolic analysis reused",
    "memory": "per tet: the per-corner buffer of the gather (48 B), Bm and Bm R^T (72 B), the quaternion, last "
              "turn and twist (32 B), the tet's corners and their adjacency slots (32 B), the damping frame R_n "
              "(16 B, with stiffness damping), rest volume and body (8 B); per vertex, fourteen vectors (the "
              "state, CG's and Newton's: 168 B, 49 B/tet on epcot); fields sized to a capacity (5 % unused on "
              "epcot); on large meshes the two-level preconditioner's dense coarse inverse (up to 768 x 768: "
              "2.4 MB in f32, 48 B/tet on box50k). 200 B/tet would need Bm R^T recomputed in every CG "
              "product or the gather's buffer replaced by atomics: both slower, and atomics would add in a "
              "different order on every run, where runs are now reproducible bit for bit",
}


def targets(results):
    """The speed targets (issue 12) with what this run measured, met or not, and what limits each."""
    by_name = {s["name"]: s for s in results["scenes"]}
    rows = []

    def add(target, goal, value, unit, met, limit):
        text = "–" if value is None else f"{value:.3g} {unit}"
        verdict = "not measured" if value is None else "reported" if met is None else "met" if met(value) else "not met"
        rows.append(f"| {target} | {goal} | {text} | {verdict} | {LIMITS.get(limit, '') if verdict == 'not met' else ''} |")

    start = results.get("startup", {})
    add("start-up, warm cache", "<= 2 s", start.get("warm_s"), "s", lambda v: v <= 2, "warm")
    add("start-up, cold cache", "(reported)", start.get("cold_s"), "s", None, "")
    add("second Simulation, same kind, to its first step", "<= 0.3 s", start.get("second_s"), "s",
        lambda v: v <= 0.3, "")
    add("second Simulation beside a live one", "(reported)", start.get("beside_s"), "s", None, "")
    add("`view`, first frame (the scene at rest), warm cache", "<= 3 s", start.get("view_first_s"), "s",
        lambda v: v <= 3, "")
    add("`view`, first stepped frame, warm cache", "(reported)", start.get("view_stepped_s"), "s", None, "")
    box = by_name.get("box50k")
    row = box and find(box, method="corotational", solver="pcg", step="single", dt_factor=1, tolerance=1e-3)
    if row:
        add("rotation extraction, box50k", "<= 15 ns/tet", 1e6 * row["rotation_ms"] / box["tets"], "ns/tet",
            lambda v: v <= 15, "rotation")
        add("box50k corotational, PCG 1e-3, one-solve step", ">= 60 steps/s", 1e3 / row["ms_median"], "steps/s",
            lambda v: v >= 60, "box50k")
        newton = find(box, method="corotational", solver="pcg", step="newton", dt_factor=1, tolerance=1e-3)
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
    epcot = by_name.get("epcot")
    row = epcot and baseline(epcot, "corotational", "newton")
    add("memory, epcot, model + state + solver", "<= 200 B/tet", row and row["bytes_per_tet"], "B/tet",
        lambda v: v <= 200, "memory")
    return ["## Targets", "",
            "Measured in this run (start-up: `app/startup.py`, medians of 3; the window on $DISPLAY or, "
            "without one, a virtual display, Xvfb). No GPU was available.", "",
            "| target | goal | measured | verdict | what limits it |", "|---|---|---:|---|---|", *rows, ""]


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


def direct_split(scene):
    """Where a direct step's time goes, per solver and method."""
    parts = []
    for r in scene["variants"]:
        if r["solver"] == "direct":
            once = "" if r["backend"] == "superlu" else f" (and once, the pattern's analysis: {r['analysis_ms']:.3g})"
            parts.append(f"{r['name']}: rotations {r['rotation_ms']:.3g}, assembly {r['assembly_ms']:.3g}, "
                         f"factorisation {r['factorise_ms']:.3g}, forces and solve {r['solve_ms']:.3g}{once}")
    return "Direct steps, ms (medians): " + "; ".join(parts) + "."


def step_name(row):
    return Variant(row["method"], row["solver"], row["step"]).step_name


# ---------------------------------------------------------------- the plot

COLOURS = {("corotational", "newton"): "tab:blue", ("corotational", "single"): "tab:purple",
           ("linear", "newton"): "tab:orange", ("linear", "single"): "tab:orange"}
LEGEND_INCHES = 1.2   # below the plots


def series(scene):
    """{(legend, colour, style): [(s per sim s, error, point label)]}: the lines of one scene's plot."""
    out = {}

    def add(row, what, style, label):
        error = final_error(row)
        if error is None:
            return
        kind = "linear" if row["method"] == "linear" else f"corotational {step_name(row)}"
        key = (f"{kind}, {what}", COLOURS[row["method"], row["step"]], style)
        out.setdefault(key, []).append((row["s_per_sim_s"], max(error, 1e-12), label))

    dts = "dt " + " / ".join(format(f * scene["dt"], "g") for f in DT_FACTORS) + " s"
    tolerances = "PCG " + " / ".join(map(sci, PCG_TOLERANCES))
    jacobi = "Jacobi x" + " / ".join(map(str, JACOBI_ITERATIONS))
    ends = (PCG_TOLERANCES[0], PCG_TOLERANCES[-1], JACOBI_ITERATIONS[0], JACOBI_ITERATIONS[-1])
    for r in scene["variants"]:   # only the ends of the tolerance and Jacobi axes are labelled: they crowd
        if r["solver"] == "pcg" and r["tolerance"] == BASELINE_TOLERANCE:
            add(r, dts, "o-", f"{r['dt']:g} s")
        if r["solver"] == "pcg" and r["dt_factor"] == 1:
            add(r, tolerances, "^--", sci(r["tolerance"]) if r["tolerance"] in ends else "")
        if r["solver"] == "jacobi":
            add(r, jacobi, "s:", f"J{r['iterations']}" if r["iterations"] in ends else "")
        if r["solver"] == "direct":   # results from before the baseline had backends have no "backend"
            add(r, "direct", "D", direct.BACKENDS[r["backend"]].label if "backend" in r else "")
    return out


def plot(results, file):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    scenes = results["scenes"]
    cols = min(3, len(scenes))
    rows = -(-len(scenes) // cols)
    height = 4.6 * rows + LEGEND_INCHES
    fig, axes = plt.subplots(rows, cols, figsize=(max(6 * cols, 11), height), squeeze=False)
    for ax, s in zip(axes.ravel(), scenes):
        lowest = min(s["reference_floor"], ERROR_GOAL)
        for (legend, colour, style), points in series(s).items():
            xs, ys, labels = zip(*points)
            lowest = min(lowest, *ys)
            ax.plot(xs, ys, style, color=colour, alpha=0.85, ms=5, label=legend)
            for x, y, label in points:
                ax.annotate(label, (x, y), fontsize=6, color=colour, textcoords="offset points", xytext=(3, 3))
        ax.axhline(ERROR_GOAL, color="green", lw=1, ls=":", label=f"the goal: {100 * ERROR_GOAL:g} % of the scene size")
        ax.axhspan(1e-12, s["reference_floor"], color="grey", alpha=0.15, lw=0,
                   label="below the reference's own error (estimate)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1, 2, 5)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(bottom=lowest / 3)
        ax.set_title(f"{s['name']} ({s['tets']} tets, scene dt {s['dt']:g} s, dt_ref {s['reference_dt']:g} s)",
                     fontsize=9)
        ax.set_xlabel("wall time per simulated second (s)")
        ax.set_ylabel(f"position error at t = {s['checkpoints'][-1]:g} s")
        ax.grid(True, which="major", alpha=0.3)
    for ax in axes.ravel()[len(scenes):]:
        ax.axis("off")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    m = results["machine"]
    fig.suptitle("Position error (RMS distance to the reference / bounding-box diagonal) against wall time per "
                 f"simulated second; {m['backend']} {m['precision']}, {m['cores']} cores\n"
                 "points: dt, PCG tolerance, Jacobi iterations (log-log: down and left is better)", fontsize=9)
    fig.tight_layout(rect=(0, LEGEND_INCHES / height, 1, 1))
    fig.savefig(file, format="png", dpi=110)
    plt.close(fig)


def write(results, out, names=RESULT_FILES):
    out = Path(out)
    with atomic_open(out / names["json"]) as f:
        json.dump(results, f, indent=1)
    with atomic_open(out / names["md"]) as f:
        f.write(markdown(results))
    with atomic_open(out / names["plot"], "wb") as f:
        plot(results, f)


# ---------------------------------------------------------------- command

def destination(args):
    """(folder, file names) the results go to: --out, or with --docs the pages in docs/, which
    it replaces (they are under version control) and which only the full plan may write."""
    if not args.docs:
        refuse_overwrite(args.out, args.overwrite)
        outputs.remove_stale_temporaries(args.out)     # what a killed run left
        return Path(args.out), RESULT_FILES
    if args.quick or args.scenes:
        raise FemError(f"--docs records the full benchmark; drop {'--quick' if args.quick else '--scenes'}")
    check_output(DOCS, "--docs", "folder")
    return DOCS, DOCS_FILES


def run(args, plan=None):
    """main.py bench; `plan` (for tests) replaces the quick or full plan."""
    folder, names = destination(args)
    backend = device.start(args)["backend"]
    plan = plan or (QUICK if args.quick else full_plan())
    if args.scenes:
        plan = replace(plan, scenes=args.scenes)
    info = machine(backend, args.precision)
    began = time.perf_counter()
    scenes = []
    runs = len(REFERENCES) + len(variants())
    with Progress(len(plan.scenes) * runs, "run", "bench") as progress:
        for ref in plan.scenes:
            scenes.append(measure_scene(ref, plan, args, progress))
    lines, numbers = headline(scenes)
    info["bench_minutes"] = (time.perf_counter() - began) / 60
    results = {"machine": info, "plan": vars(plan), "headline": lines, "headline_numbers": numbers,
               "scenes": scenes}
    if plan.stiff:
        print(f"bench: preconditioners on the stiff {plan.stiff}", file=sys.stderr)
        stiff = compare_preconditioners(stiff_bar(plan.stiff), plan.preconditioner_steps)
        results["stiff"] = {"name": plan.stiff, **STIFF, "preconditioners": stiff}
    if plan.startup:
        print(f"bench: start-up and resting cost of {plan.startup}", file=sys.stderr)
        results["startup"] = startup.measure(plan.startup)
        results["startup"]["resting_ms"] = startup.resting_cost(plan.startup)
        results["startup"].update(startup.view_seconds(plan.startup))    # {} without a display
    write(results, folder, names)
    print("\n".join(lines))
    print(f"wrote {folder / names['md']}, {names['json']}, {names['plot']} ({info['bench_minutes']:.1f} min)")
    return 0
