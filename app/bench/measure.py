"""Running the benchmark: a variant from t = 0 to its last checkpoint, the reference, a whole
scene, the preconditioners' comparison, and the machine it ran on."""

import datetime
import os
import platform
import statistics
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import taichi as ti

import fem
from app import profile
from app.bench import direct
from app.bench.conclusions import final_error, observed_orders, reference_floor, reference_order
from app.bench.plan import (BASELINE_TOLERANCE, MAX_ITERATIONS, MIN_TIMED_STEPS, REFERENCE_SETTINGS, REFERENCES,
                            checkpoint_times, direct_backends, make_scene, variants)
from fem.implicit.broad_phase import BroadPhase
from fem.implicit.contact import Contact


# ---------------------------------------------------------------- running

def field_bytes(*objects):
    """Bytes held by the Taichi fields that are attributes of `objects`."""
    return sum(f.to_numpy().nbytes for o in objects for f in vars(o).values() if isinstance(f, ti.Field))


def configure(sim, variant):
    """Set the engine up for a variant and go back to t = 0."""
    settings = replace(sim.scene.solver, dt=variant.dt(sim.scene.solver.dt), step=variant.step,
                       integrator=variant.integrator, method="pcg", max_iterations=MAX_ITERATIONS)
    if variant.solver == "reference":
        settings = replace(settings, **REFERENCE_SETTINGS)
    elif variant.solver == "pcg":
        settings = replace(settings, tolerance=variant.tolerance)
    elif variant.solver == "jacobi":   # a tolerance never reached: exactly `iterations` per step
        settings = replace(settings, method="jacobi", tolerance=1e-12, max_iterations=variant.iterations)
    else:                              # direct: the engine only measures; app.bench.direct reads dt from it
        settings = replace(settings, tolerance=BASELINE_TOLERANCE)
    settings.check(sim.scene.name)
    sim.settings = settings
    sim.set_method(variant.method)
    sim.reset()


def warm_up(sim, steps=2):
    """Compile every kernel the variants use, and the measurements, before anything is timed."""
    engine = [v for v in variants() if v.solver != "direct"]
    for variant in {(v.method, v.solver, v.step, v.integrator): v for v in engine}.values():
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
              field_bytes(sim.model, sim.state, sim.solver, *sim.solver.parts))
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
    errors = {}
    for t in map("{:g}".format, times):
        x = run["snapshots"].get(t)
        errors[t] = None if x is None else distance(x, reference[t], sim)
    row = {
        "label": f"{variant.name} ({variant.step_name}, dt {dt:g} s)", "name": variant.name,
        "method": variant.method, "solver": variant.solver, "step": variant.step,
        "integrator": variant.integrator, "dt": dt,
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


def distance(x, y, sim):
    """RMS distance of the vertices of two position arrays (n, 3), over the bounding-box diagonal at rest."""
    X = sim.model.rest_positions_np
    return rms(x - y) / float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))


def rms(d):
    return float(np.sqrt((d ** 2).sum(axis=1).mean()))


def measure_references(scene, times, plan, args, progress):
    """Rows of the reference and its twins at 2 and 4 dt_ref, the reference's {time: positions}, and
    the distance of the twins from each other at the last checkpoint (over the scene size).

    They run in f64: a bench in f32 restarts Taichi in f64 and back (which ends every
    Simulation made before; the positions are numpy arrays and outlive it)."""
    if args.precision != "f64":
        fem.init(args.arch, "f64", debug=args.debug)
    sim = fem.Simulation(scene)
    rows, runs = [], []
    for variant in REFERENCES:
        progress.set_description(f"{scene.name}: {variant.name}")
        run = run_variant(sim, variant, times, plan)
        runs.append(run["snapshots"])
        rows.append(summarise(variant, run, runs[0], sim, times, plan))
        progress.update()
    last = f"{times[-1]:g}"
    twins = distance(runs[2][last], runs[1][last], sim)
    if args.precision != "f64":
        fem.init(args.arch, args.precision, debug=args.debug)
    return rows, runs[0], twins


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
    rows, reference, twins = measure_references(scene, times, plan, args, progress)
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
    out = {"name": ref, "description": scene.description, "tets": sim.model.n_tets,
           "vertices": sim.model.n_vertices, "ground": scene.effects.ground is not None, "dt": scene.solver.dt, "reference_dt": rows[0]["dt"],
           "reference_difference": final_error(rows[1]), "twins_difference": twins,
           "reference_order": reference_order(final_error(rows[1]), twins),
           "checkpoints": times, "variants": rows, "preconditioners": preconditioners}
    out["reference_floor"] = reference_floor(out["reference_difference"], out["reference_order"])
    out["observed_order"] = observed_orders(out)
    return out


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


PROFILE_STEPS = 20      # profiled steps of each kind
PROFILE_WARMUP = 3      # steps before them: compiling, first touches


def kernel_profile(ref, args, info):
    """{"scene", "tets", "machine", "steps", "warmup", "kinds": {kind: table}}: the kernel profile
    (app/profile.py) of a BOXES bar's one-solve and default steps. Taichi restarts with its
    profiler on, which ends every Simulation made before: run it last."""
    fem.init(args.arch, args.precision, debug=args.debug, profile=True)
    sim = fem.Simulation(make_scene(ref))
    kinds = {kind: profile.profile_steps(sim, kind, PROFILE_WARMUP, PROFILE_STEPS) for kind in profile.STEP_KINDS}
    return {"scene": ref, "tets": sim.model.n_tets, "steps": PROFILE_STEPS, "warmup": PROFILE_WARMUP, "kinds": kinds,
            "machine": f"{info['cpu']}, {info['cores']} cores, {info['backend']} {info['precision']}, "
                       f"{datetime.date.today().isoformat()}"}


# ---------------------------------------------------------------- contact's cost (issue 35)

def contact_kernels():
    """The names of contact's own kernels: broad phase, step bound, first iterate, lagged friction,
    stats (Contact's and BroadPhase's; no other class of fem/ has a kernel of those names)."""
    return {name for part in (Contact, BroadPhase) for name, f in vars(part).items()
            if getattr(f, "_is_wrapped_kernel", False)}


def contact_cost(ref, plan, args, info):
    """{"scene", "bodies", "vertices", "warmup", "steps", "machine", "on", "off"}: a contact scene's steps with
    Taichi's profiler on (run after kernel_profile, which starts it), from the scene's start after
    plan.contact_steps[0] steps (the bodies land), with contact and with it off (the bodies pass
    through each other). Each of "on" and "off": ms/step median, Newton and CG iterations a step,
    steps not converged; "on" also the pairs touching a step and contact's own kernels' share of
    the step (their time over the steps' summed wall time, `contact_kernels`)."""
    if not ti.lang.impl.current_cfg().kernel_profiler:
        fem.init(args.arch, args.precision, debug=args.debug, profile=True)
    warmup, steps = plan.contact_steps
    scene = make_scene(ref)
    out = {"scene": Path(ref).stem, "bodies": len(scene.bodies), "warmup": warmup, "steps": steps,
           "machine": f"{info['cpu']}, {info['cores']} cores, {info['backend']} {info['precision']}, "
                      f"{datetime.date.today().isoformat()}"}
    own = contact_kernels()
    for key, effect in (("on", scene.effects.contact), ("off", None)):
        sim = fem.Simulation(replace(scene, effects=replace(scene.effects, contact=effect)))
        out["vertices"] = sim.model.n_vertices
        for _ in range(warmup):
            sim.step()
        profile.restart()
        rows = [sim.step() for _ in range(steps)]
        ms = statistics.median(row["wall_ms"] for row in rows)
        out[key] = {"ms_median": ms, "newton": float(np.mean([row["newton_iters"] for row in rows])),
                    "cg": float(np.mean([row["solver_iters"] for row in rows])),
                    "unconverged": sum(not row["converged"] for row in rows)}
        if effect is not None:
            table = profile.kernels()
            out[key]["pairs"] = float(np.mean([row["contact_pairs"] for row in rows]))
            wall = sum(row["wall_ms"] for row in rows)
            out[key]["kernels"] = {name: table[name]["ms"] / wall for name in own if name in table}
            out[key]["share"] = sum(out[key]["kernels"].values())
    return out
