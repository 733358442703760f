"""Block Jacobi's blocks: rebuilt once the tets turned STALE_TURN, or after an edit, never needlessly."""

import numpy as np
from test_solver import spinning

import fem
from fem.implicit import preconditioner
from fem.scene import SolverSettings


def test_block_jacobi_is_rebuilt_only_once_the_tets_turned_stale_turn(f64, monkeypatch):
    """One-solve step: no tet is ever more than STALE_TURN from the rotation its block was built
    with, a body spinning at 0.04 rad a step rebuilds about every sixth step, and PCG needs as
    many iterations as with blocks rebuilt every step."""
    iterations = {}
    for stale_turn in (0.0, preconditioner.STALE_TURN):
        monkeypatch.setattr(preconditioner, "STALE_TURN", stale_turn)
        sim = fem.Simulation(spinning("corotational", solver=SolverSettings(step="single", dt=0.01)),
                             integrator="backward-euler")     # one extraction a step, at x_n
        blocks, rotations, m = sim.solver.preconditioning, sim.solver.rotations, sim.model.n_tets
        built, build = [], blocks.build_preconditioner

        def recording(cM, cK):
            build(cM, cK)
            built.append(rotations.quaternions.to_numpy()[:m])

        monkeypatch.setattr(blocks, "build_preconditioner", recording)
        turned, total = [], 0
        for _ in range(60):
            total += sim.step()["solver_iters"]
            q = rotations.quaternions.to_numpy()[:m]         # R(x_n): what the step's solve used
            turned.append(2 * np.arccos(np.minimum(np.abs((q * built[-1]).sum(axis=1)), 1.0)).max())
        iterations[stale_turn] = total
    assert max(turned) <= preconditioner.STALE_TURN + 1e-9
    assert max(turned) > 0.5 * preconditioner.STALE_TURN          # the blocks did go stale
    assert 60 / 8 <= len(built) <= 60 / 4
    assert iterations[preconditioner.STALE_TURN] <= 1.05 * iterations[0.0]


def test_block_jacobi_is_rebuilt_after_an_impulse_a_new_state_and_a_live_edit(f64, monkeypatch):
    sim = fem.Simulation(spinning("corotational", solver=SolverSettings(step="single", dt=0.01)),
                         integrator="backward-euler")         # BDF2 restarts (and rebuilds) after edits
    builds = []
    blocks = sim.solver.preconditioning
    build = blocks.build_preconditioner
    monkeypatch.setattr(blocks, "build_preconditioner", lambda cM, cK: builds.append(1) or build(cM, cK))
    sim.step()
    edits = [lambda: None, lambda: sim.apply_impulse([0], (0.0, 1.0, 0.0)),
             lambda: sim.set_state(sim.positions(), sim.velocities()), lambda: sim.set_material(0, 3e4, 0.3),
             lambda: sim.set_method("corotational"), lambda: sim.rotations()]
    counts = []
    for edit in edits:
        edit()
        before = len(builds)
        sim.step()
        counts.append(len(builds) - before)
    assert counts == [0, 1, 1, 1, 1, 1]
