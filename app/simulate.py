"""`main.py simulate`: run a scene without any window and summarise what happened."""

import json
import statistics
import sys

import fem
from app.files import atomic_open, refuse_overwrite
from fem.mesh import mesh_quality


def build_simulation(args):
    """The Simulation the common options ask for (scene, method, solver overrides, --set)."""
    scene = fem.load_scene(args.scene, overrides=args.set)
    return fem.Simulation(scene, method=args.method, solver=args.solver, dt=args.dt,
                          tolerance=args.tol, max_iterations=args.max_iters)


def run(args):
    fem.init(args.arch, args.precision, debug=args.debug)
    sim = build_simulation(args)
    if args.stats and args.stats != "-":
        refuse_overwrite(args.stats, args.overwrite)
    rows = []
    with (atomic_open(args.stats) if args.stats and args.stats != "-" else _nullfile(args.stats)) as out:
        for _ in range(args.steps):
            sim.step()
            row = sim.stats() if out else sim.last
            if out:
                out.write(json.dumps(row) + "\n")
            rows.append(row)
    print(summary(sim, rows))
    return 0


class _nullfile:
    """Context for 'no stats file' (None) or stdout ('-')."""

    def __init__(self, target):
        self.target = sys.stdout if target == "-" else None

    def __enter__(self):
        return self.target

    def __exit__(self, *exc):
        return False


def summary(sim, rows):
    m = sim.model
    final = sim.stats()
    ms = [r["wall_ms"] for r in rows[1:]] or [r["wall_ms"] for r in rows] or [0.0]
    iters = [r["solver_iters"] for r in rows] or [0]
    lines = [f"scene {sim.scene.name}: {m.n_tets} tets, {m.n_vertices} vertices, "
             f"{len(m.bodies)} bodies, dt {sim.settings.dt:g} s, solver {sim.settings.method} "
             f"(tol {sim.settings.tolerance:g}), {fem.runtime.current().get('arch')} "
             f"{fem.runtime.current().get('precision')}"]
    for i, b in enumerate(m.bodies):
        quality = mesh_quality(sim.scene.bodies[i].mesh)
        lines.append(f"  {b.name}: {quality['tets']} tets, {quality['vertices']} vertices, "
                     f"min dihedral {quality['min_dihedral_deg']:.1f} deg, volume {quality['volume']:.4g} m^3; "
                     f"{sim.scene.bodies[i].method}, volume ratio now {final['volume_ratio'][i]:.4f}")
    not_converged = sum(not r["converged"] for r in rows)
    rejected = sum(not r["finite"] for r in rows)
    lines.append(f"{len(rows)} steps to t = {sim.t:.3f} s: {statistics.median(ms):.2f} ms/step (median), "
                 f"{statistics.mean(iters):.1f} solver iterations/step, "
                 f"{not_converged} steps not converged, {rejected} steps rejected")
    lines.append(f"energy: kinetic {final['kinetic_energy']:.4g} J, elastic {final['elastic_energy']:.4g} J; "
                 f"inverted tets {final['inverted_tets']}")
    return "\n".join(lines)
