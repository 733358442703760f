"""`main.py simulate`: run a scene without any window and summarise what happened.

With --stats FILE one JSON row per step goes to FILE (with --stats -, to stdout,
and the summary to stderr so that stdout stays pure JSON lines). An interrupted
run (Ctrl-C, SIGTERM) keeps the complete rows written so far and says so.
"""

import json
import statistics
import sys
from array import array
from pathlib import Path

import fem
import scenes
from app import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, device
from app import outputs, profile
from app.files import atomic_open, interrupts_deferred, refuse_overwrite
from app.compiling import Compiling, start_key
from app.progress import Progress
from fem.implicit.integrators import described
from fem.mesh import mesh_quality
from fem.simulation import MAX_SPLITS, SUNK


def build_simulation(args):
    """The Simulation the common options ask for (scene, method, solver overrides, --set)."""
    scene = scenes.load_scene(args.scene, overrides=args.set, contact=getattr(args, "contact", False))
    return fem.Simulation(scene, method=args.method, solver=args.solver, dt=args.dt,
                          tolerance=args.tol, max_iterations=args.max_iters, step=args.step,
                          integrator=args.integrator)


def run(args) -> int:
    """Run the steps `args` asks for; returns the exit code."""
    to_file = args.stats is not None and args.stats != "-"
    if to_file:
        refuse_overwrite(args.stats, args.overwrite)
        for note in outputs.rescue_rows(Path(args.stats)):
            print(note, file=sys.stderr)
    device.start(args)
    with Compiling(Path(args.scene).stem, start_key(args)) as compiling:
        sim = build_simulation(args)
        return run_steps(args, sim, compiling)


def run_steps(args, sim, compiling):
    """The steps, the rows and the summary of `simulate`; `compiling` is done after the first step."""
    to_file = args.stats is not None and args.stats != "-"
    rows, compiled_later = Tally(), []
    # The summary goes where it does not mix with the rows.
    report = sys.stderr if args.stats == "-" else sys.stdout
    try:
        with (atomic_open(args.stats, keep_if_interrupted=True, overwrite=args.overwrite) if to_file else _nullfile(args.stats)) as out, \
                Progress(args.steps, "step", sim.scene.name) as progress:
            for step in range(args.steps):
                sim.step()
                compiling.done()
                row = sim.stats() if out else sim.last
                with interrupts_deferred():      # the row in the file and the count move together
                    if out:
                        out.write(json.dumps(row) + "\n")
                    rows.append(row)
                progress.update()
                if args.profile and step == 0:
                    profile.restart()         # the first step compiles and touches memory first
                    fem.runtime.compile_listeners().append(compiled_later.append)
    except KeyboardInterrupt:
        kept = f"; kept its {len(rows)} complete rows in {args.stats}" if to_file else ""
        at = f"at step {len(rows) + 1} of {args.steps}" if len(rows) < args.steps else "after its last step"
        print(f"interrupted {at}{kept}", file=sys.stderr)
        if rows:
            print(summary(sim, rows), file=report)
        return EXIT_INTERRUPTED
    if compiled_later.append in fem.runtime.compile_listeners():
        fem.runtime.compile_listeners().remove(compiled_later.append)
    table = profile_table(rows, compiled_later) if args.profile else None    # before the summary's own kernels
    print(summary(sim, rows), file=report)
    if table:
        print(table, file=report)
    return check_rejected(rows, sim.settings.dt)


def launches_line(table, rows, steps):
    """'launches: 412 device tasks a step; 2.0 Newton iterations a step, 206 tasks each; 31.5 PCG
    iterations a step, cg_iterations 1.4 tasks each': what bounds a small step on a GPU, where each
    task costs a launch (docs/gpu.md). rows: the steps' columns, the first (not profiled) left out."""
    tasks = sum(r["tasks"] for r in table)
    newton, cg = sum(rows["newton_iters"][1:]), sum(rows["solver_iters"][1:])
    cg_tasks = sum(r["tasks"] for r in table if r["kernel"] == "cg_iterations")
    return (f"launches: {tasks / steps:.0f} device tasks a step; {newton / steps:.1f} Newton iterations a step, "
            f"{tasks / newton if newton else 0:.0f} tasks each; {cg / steps:.1f} PCG iterations a step, "
            f"cg_iterations {cg_tasks / cg if cg else 0:.1f} tasks each")


def profile_table(rows, compiled_later=()):
    """The kernel profile of the steps after the first (which compiles the kernels), with each
    kernel's share of those steps' wall time; a line saying why there is none with fewer than
    two steps. compiled_later: the kernels that compiled in the profiled steps (a line search's
    trial that the first step did not need), whose compiling is in the time outside kernels."""
    wall = rows["wall_ms"][1:]
    if not wall:
        return (f"kernel profile: none, as the run took {counted(len(rows), 'step')}: the first step "
                f"compiles the kernels and is left out, so --profile needs --steps 2 or more")
    steps, total = len(wall), sum(wall)
    table = profile.rows(profile.kernels(), steps, total)
    return (f"kernel profile of the {counted(steps, 'step')} after the first ({statistics.median(wall):.2f} ms/step "
            f"median, {total:.1f} ms in all, with the profiler on):\n"
            + profile.markdown(table, steps, total) + "\n" + launches_line(table, rows, steps)
            + (f"\n{counted(len(compiled_later), 'kernel')} compiled during these steps (the first step did not "
               f"need them); their compiling is counted outside kernels: profile more steps to make it a small "
               f"share" if compiled_later else ""))


class Tally:
    """What the summary needs of every step (time, iterations, converged, finite), kept as
    compact columns: a million steps take 50 MB, not the 0.8 GB of their stats rows."""

    KEYS = {"wall_ms": "d", "solver_iters": "d", "newton_iters": "d", "converged": "b", "finite": "b",
            "energy_limited": "d", "restarted": "d", "solver_capped": "d"}

    def __init__(self):
        self.columns = {key: array(code) for key, code in self.KEYS.items()}

    def append(self, row):
        for key, column in self.columns.items():
            column.append(row[key])

    def __iadd__(self, rows):
        for row in rows:
            self.append(row)
        return self

    def __len__(self):
        return len(self.columns["finite"])

    def __getitem__(self, key):
        """The column of one key, e.g. tally["wall_ms"]."""
        return self.columns[key]


def check_rejected(rows, dt) -> int:
    """The exit code of a run by its steps: EXIT_FAILED, with an error line, when every step
    was rejected (non-finite values: nothing was simulated); a warning when some were."""
    rejected = len(rows) - sum(rows["finite"])
    if rows and rejected == len(rows):
        print(f"error: every one of the {len(rows)} steps was rejected (non-finite values), so nothing "
              f"moved; the time step dt = {dt:g} s is probably far too large for this scene: "
              f"try a smaller --dt", file=sys.stderr)
        return EXIT_FAILED
    if rejected:
        print(f"warning: {rejected} of {len(rows)} steps were rejected (non-finite values) and the "
              f"state before each kept; a smaller --dt may help", file=sys.stderr)
    return EXIT_OK


class _nullfile:
    """Context for 'no stats file' (None) or stdout ('-')."""

    def __init__(self, target):
        self.target = sys.stdout if target == "-" else None

    def __enter__(self):
        return self.target

    def __exit__(self, *exc):
        return False


def preconditioner_note(sim):
    """', two-level preconditioner' (PCG only)."""
    name = sim.solver.preconditioner
    return f", {name} preconditioner" if name else ""


def tolerance_note(settings):
    """"1e-4", or "1e-4, 2.5e-05 at this dt": the tolerance set, and the one the steps take where
    it follows a dt below 0.02 s (SolverSettings.tolerances_at)."""
    taken = settings.tolerances_at(settings.dt)[0]
    return f"{settings.tolerance:g}" + (f", {taken:.3g} at this dt" if taken < settings.tolerance else "")


def integrator_note(sim):
    """"trapezoidal (auto)": the integrator the steps take (with its rho_infinity where it has
    numerical dissipation), and whether "auto" chose it."""
    switches = sim.solver.switches
    integrator = described(sim.settings, sim.solver.effects.damped, switches.ground or switches.contact)
    return integrator + (" (auto)" if sim.settings.integrator == "auto" else "")


def summary(sim, rows):
    m = sim.model
    final = sim.stats()
    ms = rows["wall_ms"][1:] or rows["wall_ms"] or [0.0]
    iters = rows["solver_iters"] or [0]
    lines = [f"scene {sim.scene.name}: {m.n_tets} tets, {m.n_vertices} vertices, "
             f"{counted(len(m.bodies), 'body', 'bodies')}, dt {sim.settings.dt:g} s, {integrator_note(sim)}, solver {sim.settings.method} "
             f"(tol {tolerance_note(sim.settings)}{preconditioner_note(sim)}), {fem.runtime.current().get('arch')} "
             f"{fem.runtime.current().get('precision')}"]
    for i, b in enumerate(m.bodies):
        quality = mesh_quality(sim.scene.bodies[i].mesh)
        lines.append(f"  {b.name}: {quality['tets']} tets, {quality['vertices']} vertices, "
                     f"min dihedral {quality['min_dihedral_deg']:.1f} deg, volume {quality['volume']:.4g} m^3; "
                     f"{sim.model.bodies[i].method}, volume ratio now {final['volume_ratio'][i]:.4f}")
    not_converged = len(rows) - sum(rows["converged"])
    rejected = len(rows) - sum(rows["finite"])
    lines.append(f"{counted(len(rows), 'step')} to t = {sim.t:.3f} s: {statistics.median(ms):.2f} ms/step (median), "
                 f"{statistics.mean(rows['newton_iters'] or [0]):.1f} Newton and "
                 f"{statistics.mean(iters):.1f} solver iterations/step ({sim.step_kind} step), "
                 f"{counted(not_converged, 'step')} not converged{fallback_note(rows)}{capped_note(sim, rows)}, "
                 f"{counted(rejected, 'step')} rejected")
    lines.append(f"energy: {energy_terms(sim, final)}; inverted tets {final['inverted_tets']}")
    if sim.solver.switches.contact:
        record, smallest = sim.contact_record, sim.contact_record["smallest_distance"]
        lines.append(f"contact (distance {sim.scene.effects.contact.distance:g} m): at most {record['most_pairs']} "
                     f"pairs touching, smallest distance "
                     f"{'none closer than the distance' if smallest is None else f'{smallest:.3g} m'}, "
                     f"{counted(record['interpenetrating_steps'], 'step')} ended with interpenetrating pairs")
    if sim.solver.switches.ground and (sim.ground_record["split_steps"] or sim.ground_record["sunk_steps"]):
        split, sunk = sim.ground_record["split_steps"], sim.ground_record["sunk_steps"]
        lines.append(f"ground: {counted(split, 'step')} taken in sub-steps (dt / 2, / 4, ... / {2 ** MAX_SPLITS}) "
                     f"where one would have sunk into it; {counted(sunk, 'step')} failed, ending with vertices "
                     f"deeper than {SUNK:.0%} of their body's size" + (": try a smaller dt" if sunk else ""))
    return "\n".join(lines)


def fallback_note(rows):
    """' (of them 3 with a rigid step instead of the solve's), 1 step by backward Euler after a strained
    body's failed one': the steps whose solve failed for some body, which the safeguards replaced
    (fem/implicit/safeguards.py), and the steps after a strained body's failed second-order one,
    which backward Euler took (ImplicitSolver.step)."""
    trimmed = sum(1 for n in rows["energy_limited"] if n > 0)
    restarted = sum(1 for n in rows["restarted"] if n > 0)
    return (f" (of them {trimmed} with a rigid step instead of the solve's)" if trimmed else "") + \
        (f", {counted(restarted, 'step')} by backward Euler after a strained body's failed one" if restarted else "")


def capped_note(sim, rows):
    """'; the linear solve stopped at its cap of 400 iterations, unconverged, in 780 of 780 Newton
    iterations': where some did (solver.max_iterations, --max-iters), which leaves their Newton
    directions inexact."""
    capped, newton = int(sum(rows["solver_capped"])), int(sum(rows["newton_iters"]))
    return (f"; the linear solve stopped at its cap of {counted(sim.settings.max_iterations, 'iteration')}, "
            f"unconverged, in {capped} of {counted(newton, 'Newton iteration')}") if capped else ""


ENERGY_TERMS = (("kinetic", "kinetic_energy"), ("elastic", "elastic_energy"),
                ("gravity", "gravity_energy"), ("contact", "contact_energy"))


def energy_terms(sim, final):
    """'kinetic 215 J, elastic 54.56 J, gravity 3575 J, total 3845 J': every term the total
    holds (gravity's potential with gravity on, contact's barrier with a ground or contact),
    so that the printed terms add up to the total."""
    switches = sim.solver.switches
    shown = {"kinetic_energy": True, "elastic_energy": True, "gravity_energy": switches.gravity,
             "contact_energy": switches.ground or switches.contact}
    terms = [f"{name} {final[key]:.4g} J" for name, key in ENERGY_TERMS
             if shown[key] or final[key] != 0.0]
    return ", ".join(terms + [f"total {final['total_energy']:.4g} J"])


def counted(count, noun, plural=None):
    """'1 step', '2 steps', '1 body', '3 bodies'."""
    return f"{count} {noun if count == 1 else plural or noun + 's'}"
