"""`main.py bench`: what accuracy costs in time.

Every scene runs once as a reference (corotational, PCG at a tolerance as tight
as the precision allows, SVD rotations), then once per variant over the same
simulated time from the same start:

    linear and corotational FEM, each with
        PCG at tolerances 1e-2, 1e-3, 1e-4, 1e-6      (matrix-free, fem.solver)
        Jacobi iteration at 10, 30, 100 iterations     (matrix-free, fem.solver)
        a direct sparse solver                         (assembled and factorised, app.direct)

A variant's accuracy is its position error against the reference at fixed
times; its cost is the wall time of a step, measured after warm-up (Taichi
compiles its kernels on first use, and a step's first run builds one-off data).
Outputs: results.md (tables), results.json (every number), accuracy_vs_time.png.
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
from tqdm import tqdm

import fem
import scenes
from app import device, direct
from app.files import atomic_open, refuse_overwrite
from assets.generators import box
from fem.scene import Body, Effects, Initial, Material, Scene, Selection, SolverSettings, place_mesh

PCG_TOLERANCES = (1e-2, 1e-3, 1e-4, 1e-6)
JACOBI_ITERATIONS = (10, 30, 100)
REFERENCE_TOLERANCE = {"f64": 1e-10, "f32": 1e-7}   # f32 stalls near its rounding error
MAX_ITERATIONS = 1000         # PCG: the tolerance, not the cap, ends a solve
BASELINE_TOLERANCE = 1e-4     # the scenes' default: corotation's extra cost is compared here
ERROR_GOAL = 1e-3             # accurate enough: RMS position error under 0.1 % of the bounding-box diagonal
MIN_TIMED_STEPS = 3           # a variant stopped by the time budget still times this many steps
BOXES = {"box80": 2, "box1k": 5, "box10k": 10, "box50k": 17}   # 2 x 1 x 1 m bar, 2k x k x k cells


@dataclass
class Plan:
    """How much to measure."""

    scenes: list          # built-in names, scene files or BOXES names
    checkpoints: tuple    # s: positions are compared with the reference at these times; the last ends a run
    warmup_steps: int     # first steps of every run left out of the timings
    budget_s: float       # wall time after which a variant stops early (the reference never does)


def full_plan():
    return Plan([*scenes.builtin_scenes(), "box1k", "box10k", "box50k"], (0.5, 1.0, 2.0), 2, 45.0)


QUICK = Plan(["cube86", "box1k"], (0.5, 1.0), 2, 10.0)
TEST = Plan(["box80"], (0.1, 0.2), 2, 10.0)        # for tests/test_bench.py: seconds, not minutes


@dataclass
class Variant:
    method: str               # "linear" | "corotational"
    solver: str               # "reference" | "pcg" | "jacobi" | "direct"
    tolerance: float = 0.0    # pcg, reference
    iterations: int = 0       # jacobi

    @property
    def label(self):
        setting = {"reference": f"reference (PCG {sci(self.tolerance)})", "pcg": f"PCG {sci(self.tolerance)}",
                   "jacobi": f"Jacobi x{self.iterations}", "direct": "direct"}[self.solver]
        return setting if self.solver == "reference" else f"{self.method} {setting}"

    @property
    def short(self):
        """Label beside a point in the plot."""
        return {"reference": "ref", "pcg": sci(self.tolerance), "jacobi": f"J{self.iterations}",
                "direct": "direct"}[self.solver]


def sci(x):
    """1e-04 -> 1e-4."""
    return f"{x:.0e}".replace("e-0", "e-").replace("e+0", "e")


def variants(precision):
    out = [Variant("corotational", "reference", REFERENCE_TOLERANCE[precision])]
    for method in ("corotational", "linear"):
        out += [Variant(method, "pcg", tol) for tol in PCG_TOLERANCES]
        out += [Variant(method, "jacobi", iterations=k) for k in JACOBI_ITERATIONS]
        out.append(Variant(method, "direct"))
    return out


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


# ---------------------------------------------------------------- running

def field_bytes(*objects):
    """Bytes held by the Taichi fields that are attributes of `objects`."""
    return sum(f.to_numpy().nbytes for o in objects for f in vars(o).values() if isinstance(f, ti.Field))


def configure(sim, variant):
    """Set the engine up for an engine variant and go back to t = 0."""
    # every variant takes the one-solve step, the step the direct baseline takes (a Newton axis: to do)
    settings = replace(sim.scene.solver, max_iterations=MAX_ITERATIONS, step="single")
    if variant.solver == "reference":
        settings = replace(settings, method="pcg", tolerance=variant.tolerance, rotations="svd")
    elif variant.solver == "pcg":
        settings = replace(settings, method="pcg", tolerance=variant.tolerance)
    elif variant.solver == "jacobi":   # a tolerance never reached: exactly `iterations` per step
        settings = replace(settings, method="jacobi", tolerance=1e-12, max_iterations=variant.iterations)
    settings.check(sim.scene.name)
    sim.settings = settings
    sim.set_method(variant.method)
    sim.reset()


def warm_up(sim, precision, steps=2):
    """Compile every kernel the variants use before anything is timed."""
    engine = [v for v in variants(precision) if v.solver != "direct"]
    for variant in {(v.method, v.solver): v for v in engine}.values():
        configure(sim, variant)
        for _ in range(steps):
            sim.step()


def run_variant(sim, variant, n_steps, checkpoint_steps, plan):
    """Step one variant from t = 0; returns per-step infos, {step: positions} at the checkpoints,
    the volume and energy drift, the memory its solver holds (bytes) and whether it stopped early."""
    configure(sim, Variant(variant.method, "pcg", BASELINE_TOLERANCE) if variant.solver == "direct" else variant)
    if variant.solver == "direct":
        solver = direct.DirectSolver(sim)
        step = solver.step

        def observe():
            sim.state.load(solver.x, solver.v)   # the engine measures the direct solver's state too
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
            snapshots[k] = x
        out_of_time = time.perf_counter() - start > plan.budget_s and variant.solver != "reference"
        if out_of_time and k >= plan.warmup_steps + MIN_TIMED_STEPS:
            break
    energy = sum_energy(stats)
    memory = solver.memory_bytes if variant.solver == "direct" else field_bytes(sim.model, sim.state, sim.solver)
    return {"infos": infos, "snapshots": snapshots, "volume_drift": volume_drift,
            "energy_drift": energy / energy0 - 1 if energy0 > 0 else None,
            "memory_bytes": memory, "stopped_early": len(infos) < n_steps}


def sum_energy(stats):
    return stats["kinetic_energy"] + stats["elastic_energy"]


def summarise(variant, run, reference, sim, checkpoint_steps, plan):
    """One table row: timings after warm-up, iterations, memory and errors against the reference."""
    timed = run["infos"][plan.warmup_steps:]
    ms = [i["wall_ms"] for i in timed]
    n_tets = sim.model.n_tets
    X = sim.model.rest_positions_np
    diagonal = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
    errors = {}
    for k, t in checkpoint_steps.items():
        x = run["snapshots"].get(k)
        errors[f"{t:g}"] = None if x is None else rms(x - reference[k]) / diagonal
    row = {
        "label": variant.label, "short": variant.short, "method": variant.method, "solver": variant.solver,
        "tolerance": variant.tolerance or None, "iterations": variant.iterations or None,
        "steps": len(run["infos"]), "timed_steps": len(timed), "stopped_early": run["stopped_early"],
        "first_step_ms": run["infos"][0]["wall_ms"],
        "ms_median": statistics.median(ms), "ms_min": min(ms), "ms_max": max(ms),
        "rotation_ms": statistics.median(i["rotation_ms"] for i in timed),
        "bytes_per_tet": run["memory_bytes"] / n_tets,
        "errors": errors, "volume_drift": run["volume_drift"], "energy_drift": run["energy_drift"],
    }
    if variant.solver == "direct":
        row["factorise_ms"] = statistics.median(i["factorise_ms"] for i in timed)
    else:
        iters = [i["solver_iters"] for i in timed]
        per_iter = statistics.median(i["solve_ms"] / max(i["solver_iters"], 1) for i in timed)
        row.update(iters_per_step=statistics.mean(iters), ms_per_iter=per_iter,
                   ns_per_tet_iter=1e6 * per_iter / n_tets,
                   converged=sum(i["converged"] for i in timed) / len(timed))
    return row


def rms(d):
    return float(np.sqrt((d ** 2).sum(axis=1).mean()))


def measure_scene(ref, plan, precision, progress):
    progress.set_description(f"{ref}: building")
    sim = fem.Simulation(make_scene(ref))
    dt = sim.settings.dt
    checkpoint_steps = {max(1, round(t / dt)): t for t in plan.checkpoints}
    n_steps = max(*checkpoint_steps, plan.warmup_steps + MIN_TIMED_STEPS)
    progress.set_description(f"{ref}: compiling")
    warm_up(sim, precision)
    rows, reference = [], None
    for variant in variants(precision):
        progress.set_description(f"{ref}: {variant.label}")
        run = run_variant(sim, variant, n_steps, checkpoint_steps, plan)
        if variant.solver == "reference":
            reference = run["snapshots"]
        rows.append(summarise(variant, run, reference, sim, checkpoint_steps, plan))
        progress.update()
    return {"name": ref, "description": sim.scene.description, "tets": sim.model.n_tets,
            "vertices": sim.model.n_vertices, "dt": dt, "steps": n_steps,
            "checkpoints": list(plan.checkpoints), "variants": rows}


# ---------------------------------------------------------------- conclusions

def find(scene, method, solver, tolerance=None):
    for row in scene["variants"]:
        if (row["method"], row["solver"]) == (method, solver) and tolerance in (None, row["tolerance"]):
            return row
    return None


def final_error(row):
    return list(row["errors"].values())[-1]


def corotation_cost(scene, solver, tolerance=None):
    """Extra time per step of corotational over linear FEM with one solver, in %."""
    corot, linear = find(scene, "corotational", solver, tolerance), find(scene, "linear", solver, tolerance)
    return 100 * (corot["ms_median"] / linear["ms_median"] - 1)


def sweet_spot(scene):
    """The loosest PCG tolerance whose corotational run stays within ERROR_GOAL of the reference."""
    for tol in PCG_TOLERANCES:
        error = final_error(find(scene, "corotational", "pcg", tol))
        if error is not None and error <= ERROR_GOAL:
            return tol
    return None


def frontier(scene):
    """Variants no other variant beats in both time and accuracy (at the last checkpoint)."""
    rows = [r for r in scene["variants"] if r["solver"] != "reference" and final_error(r) is not None]
    return [r["label"] for r in sorted(rows, key=lambda r: r["ms_median"])
            if not any(o["ms_median"] < r["ms_median"] and final_error(o) <= final_error(r) for o in rows)]


def headline(scenes):
    """The measured answers, as sentences and as numbers."""
    matrix_free = [corotation_cost(s, "pcg", BASELINE_TOLERANCE) for s in scenes]
    with_direct = [corotation_cost(s, "direct") for s in scenes]
    spots = [sweet_spot(s) for s in scenes]
    found = [t for t in spots if t is not None]
    numbers = {"corotation_cost_pcg_pct": statistics.median(matrix_free),
               "corotation_cost_direct_pct": statistics.median(with_direct),
               "sweet_spot_tolerance": Counter(found).most_common(1)[0][0] if found else None}
    n = len(scenes)
    over = f" (median over {n} scenes, {min(matrix_free):.0f} to {max(matrix_free):.0f} %)" if n > 1 else ""
    over_direct = f" ({min(with_direct):.0f} to {max(with_direct):.0f} %)" if n > 1 else ""
    lines = [f"Corotation costs {numbers['corotation_cost_pcg_pct']:.0f} % more per step than linear with the "
             f"matrix-free solver (PCG {sci(BASELINE_TOLERANCE)}){over}, and "
             f"{numbers['corotation_cost_direct_pct']:.0f} % with the direct solver{over_direct}."]
    tol = numbers["sweet_spot_tolerance"]
    if tol is None:
        lines.append(f"No PCG tolerance up to {sci(PCG_TOLERANCES[-1])} kept the position error under "
                     f"{100 * ERROR_GOAL:g} % of the scene size: the frontier lies at tighter tolerances.")
    else:
        tightest = PCG_TOLERANCES[-1]
        sentence = (f"The sweet spot is PCG at {sci(tol)}: the loosest tolerance that keeps corotational "
                    f"positions within {100 * ERROR_GOAL:g} % of the scene size of the reference in "
                    f"{spots.count(tol)} of {n} scenes, at {100 * ratio(scenes, tol, tightest, 'ms_median'):.0f} "
                    f"% of the time per step of {sci(tightest)}")
        looser = PCG_TOLERANCES.index(tol) - 1
        if looser >= 0:
            other = PCG_TOLERANCES[looser]
            saving = 1 - 1 / ratio(scenes, tol, other, "ms_median")
            sentence += (f"; {sci(other)} would save {100 * saving:.0f} % of the time per step "
                         f"for {1 / ratio(scenes, tol, other, 'error'):.0f} times the error")
        lines.append(sentence + " (medians over the scenes).")
    return lines, numbers


def ratio(scenes, tol, other, key):
    """Median over scenes of (corotational PCG at tol) / (corotational PCG at other), for ms or error."""
    def value(s, t):
        row = find(s, "corotational", "pcg", t)
        return final_error(row) if key == "error" else row[key]
    pairs = [(value(s, tol), value(s, other)) for s in scenes]
    return statistics.median(a / b for a, b in pairs if a and b)


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
            "direct_solver": f"{direct.FACTORISATION}, float64", "python": platform.python_version(),
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


def markdown(results):
    m, lines = results["machine"], []
    lines += ["# What accuracy costs in time", ""]
    lines += [f"- {line}" for line in results["headline"]]
    lines += ["", f"Machine: {m['cpu']}, {m['cores']} cores (load average {m['load_average']:.1f} at the start)"
              + (f", GPU {m['gpu']}" if m.get("gpu") else "") + f"; Taichi {m['taichi']} on {m['backend']}, "
              f"{m['precision']}; direct solver {m['direct_solver']}; Python {m['python']}; {m['date']}.", ""]
    lines += [
        "Each variant runs from the same start for the same simulated time. *ms/step*: wall time per step "
        f"(median, min-max) after {results['plan']['warmup_steps']} warm-up steps, Taichi kernels compiled "
        "beforehand; *iters*: solver iterations per step (mean); *ms/iter* and *ns/tet/iter*: a step's solve "
        "time per iteration; *rot ms*: rotation extraction per step; *B/tet*: memory of the solver's data "
        "(Taichi fields of model, state and solver; for the direct solver the matrix and its factor); "
        "*err t*: RMS vertex distance to the reference at time t, divided by the bounding-box diagonal; "
        "*vol*: largest |volume / rest volume - 1| of any body; *energy*: (kinetic + elastic) energy at the "
        "end over its start value, minus 1. A blank (–) error: the variant stopped early on its time budget "
        f"({results['plan']['budget_s']:g} s).", ""]
    lines += ["## Summary", "",
              f"| scene | tets | dt (s) | corotation's extra cost, PCG {sci(BASELINE_TOLERANCE)} | "
              f"with the direct solver | sweet spot | its ms/step | its error | direct corotational ms/step |",
              "|---|---:|---:|---:|---:|---|---:|---:|---:|"]
    for s in results["scenes"]:
        tol = sweet_spot(s)
        spot = find(s, "corotational", "pcg", tol) if tol else None
        lines.append(f"| {s['name']} | {s['tets']} | {s['dt']:g} | {corotation_cost(s, 'pcg', BASELINE_TOLERANCE):+.0f} % "
                     f"| {corotation_cost(s, 'direct'):+.0f} % | {sci(tol) if tol else 'none'} "
                     f"| {fmt(spot and spot['ms_median'])} | {fmt(spot and final_error(spot), '.2e')} "
                     f"| {fmt(find(s, 'corotational', 'direct')['ms_median'])} |")
    for s in results["scenes"]:
        times = [f"err {t:g} s" for t in s["checkpoints"]]
        lines += ["", f"## {s['name']}", "",
                  f"{s['description']} {s['tets']} tets, {s['vertices']} vertices, dt {s['dt']:g} s, "
                  f"{s['steps']} steps.", "",
                  "| variant | ms/step | min-max | iters | ms/iter | ns/tet/iter | rot ms | B/tet | "
                  + " | ".join(times) + " | vol | energy |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|" + "---:|" * len(times) + "---:|---:|"]
        for r in s["variants"]:
            lines.append(
                f"| {r['label']} | {r['ms_median']:.3g} | {r['ms_min']:.3g}-{r['ms_max']:.3g} "
                f"| {fmt(r.get('iters_per_step'))} | {fmt(r.get('ms_per_iter'))} | {fmt(r.get('ns_per_tet_iter'), '.0f')} "
                f"| {r['rotation_ms']:.3g} | {r['bytes_per_tet']:.0f} | "
                + " | ".join(fmt(e, ".2e") for e in r["errors"].values())
                + f" | {r['volume_drift']:.2e} | {fmt(r['energy_drift'], '+.2e')} |")
        lines += ["", "Frontier (no variant is both faster and more accurate): " + ", ".join(frontier(s)) + "."]
    lines += ["", "![error against time per step](accuracy_vs_time.png)", ""]
    return "\n".join(lines)


def plot(results, file):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, NullFormatter

    scenes = results["scenes"]
    cols = min(3, len(scenes))
    rows = -(-len(scenes) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.5 * cols, 4.5 * rows), squeeze=False)
    colours = {"corotational": "tab:blue", "linear": "tab:orange"}
    markers = {"pcg": "o", "jacobi": "s", "direct": "D"}
    floor = 1e-9   # errors below this (the reference's own noise) are drawn on it
    for ax, s in zip(axes.ravel(), scenes):
        by_solver = {}
        for r in s["variants"]:
            if r["solver"] == "reference":
                ax.axvline(r["ms_median"], color="grey", ls="--", lw=1)
                ax.annotate("reference", (r["ms_median"], 0.02), xycoords=("data", "axes fraction"),
                            rotation=90, fontsize=7, color="grey", xytext=(2, 0), textcoords="offset points")
                continue
            error = final_error(r)
            if error is None:
                continue
            y = max(error, floor)
            by_solver.setdefault((r["method"], r["solver"]), []).append((r["ms_median"], y))
            ax.annotate(r["short"], (r["ms_median"], y), fontsize=7, textcoords="offset points",
                        xytext=(4, 3) if r["method"] == "corotational" else (4, -9))
        for (method, solver), points in sorted(by_solver.items()):
            xs, ys = zip(*points)
            ax.plot(xs, ys, marker=markers[solver], color=colours[method], ls="-" if solver != "direct" else "",
                    alpha=0.85, label=f"{method} {solver}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.axhline(ERROR_GOAL, color="green", lw=0.8, ls=":")
        ax.set_title(f"{s['name']} ({s['tets']} tets)", fontsize=10)
        ax.set_xlabel("ms per step (median)")
        ax.set_ylabel(f"position error at t = {s['checkpoints'][-1]:g} s")
        ax.grid(True, which="major", alpha=0.3)
    for ax in axes.ravel()[len(scenes):]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7, loc="best")
    m = results["machine"]
    fig.suptitle(f"Position error (RMS / bounding-box diagonal) against time per step\n"
                 f"dotted: the {100 * ERROR_GOAL:g} % goal; {m['backend']} {m['precision']}, {m['cores']} cores",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(file, format="png", dpi=110)
    plt.close(fig)


def write(results, out):
    out = Path(out)
    with atomic_open(out / "results.json") as f:
        json.dump(results, f, indent=1)
    with atomic_open(out / "results.md") as f:
        f.write(markdown(results))
    with atomic_open(out / "accuracy_vs_time.png", "wb") as f:
        plot(results, f)


# ---------------------------------------------------------------- command

def run(args, plan=None):
    """main.py bench; `plan` (for tests) replaces the quick or full plan."""
    refuse_overwrite(args.out, args.overwrite)
    backend = device.start(args)["backend"]
    plan = plan or (QUICK if args.quick else full_plan())
    if args.scenes:
        plan = replace(plan, scenes=args.scenes)
    info = machine(backend, args.precision)
    began = time.perf_counter()
    scenes = []
    with tqdm(total=len(plan.scenes) * len(variants(args.precision)), unit="run", file=sys.stderr) as progress:
        for ref in plan.scenes:
            scenes.append(measure_scene(ref, plan, args.precision, progress))
    lines, numbers = headline(scenes)
    info["bench_minutes"] = (time.perf_counter() - began) / 60
    results = {"machine": info, "plan": vars(plan), "headline": lines, "headline_numbers": numbers,
               "scenes": scenes}
    write(results, args.out)
    print("\n".join(lines))
    print(f"wrote {Path(args.out) / 'results.md'}, results.json, accuracy_vs_time.png "
          f"({info['bench_minutes']:.1f} min)")
    return 0
