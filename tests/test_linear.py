"""The linear solvers: PCG to the tolerance it reports, an iteration cap reported, Jacobi
iteration reaching PCG's answer."""

import numpy as np
import pytest
from conftest import box_mesh
from test_elastic import assembled_matrix
from test_solver import spinning

import fem
from fem.scene import Body, Effects, Initial, Material, Scene, Selection, SolverSettings


def test_pcg_reaches_tolerance_and_reports_iterations(f64):
    """A single backward Euler step solves H v' = M v + dt f(x) to the tolerance it reports (no
    gravity, no damping)."""
    scene = spinning("corotational", solver=SolverSettings(dt=0.02, tolerance=1e-8, max_iterations=400,
                                                           step="single", integrator="backward-euler"))
    scene.initial.append(Initial(Selection(None), "stretch", (np.array([1.0, 0, 0]), 1.3)))
    sim = fem.Simulation(scene)
    x, v = sim.positions(), sim.velocities()
    momentum, impulse = sim.model.mass_np[:, None] * v, 0.02 * sim.forces(x)
    info = sim.step()
    residual = momentum + impulse - sim.apply_matrix(sim.velocities(), x=x)
    true_residual = np.linalg.norm(residual) / np.sqrt(np.sum(momentum ** 2) + np.sum(impulse ** 2))
    assert info["converged"] and 0 < info["solver_iters"] < 400 and info["newton_iters"] == 1
    assert info["residual"] <= 1e-8
    assert true_residual == pytest.approx(info["residual"], rel=1e-3, abs=1e-12)


def test_iteration_cap_is_reported_not_hidden(f64):
    scene = spinning("corotational", solver=SolverSettings(dt=0.02, tolerance=1e-12, max_iterations=3,
                                                           step="single"))
    scene.initial.append(Initial(Selection(None), "stretch", (np.array([1.0, 0, 0]), 1.3)))
    info = fem.Simulation(scene).step()
    assert info["solver_iters"] == 3 and not info["converged"] and info["residual"] > 1e-12


def test_jacobi_converges_to_the_pcg_solution(f64):
    solutions = {}
    for solver in ("pcg", "jacobi"):
        scene = spinning("corotational", solver=SolverSettings(dt=0.01, method=solver, tolerance=1e-9,
                                                               max_iterations=5000, newton_tolerance=1e-9))
        scene.initial.append(Initial(Selection(None), "stretch", (np.array([1.0, 0, 0]), 1.3)))
        sim = fem.Simulation(scene)
        info = sim.step()
        assert info["converged"], info
        solutions[solver] = sim.velocities()
    np.testing.assert_allclose(solutions["jacobi"], solutions["pcg"], atol=1e-6)


def test_each_body_runs_a_pcg_of_its_own(f64):
    """Bodies that nothing couples solve H d = -grad E each with PCG scalars of their own
    (fem/implicit/linear.py: body_iteration): a body's iterates do not depend on the bodies beside
    it (bit for bit, whichever partner it has), the solve takes as many iterations as its slowest
    body, and each body's residual, against the matrix assembled with scipy, meets the tolerance
    on its own. With one set of scalars for all, a soft body beside a stiff one iterated at the
    stiff one's pace and its answer depended on its partner."""
    settings = SolverSettings(dt=0.02, tolerance=1e-8, max_iterations=2000, step="single",
                              integrator="backward-euler")
    materials = {"soft": (2e4, 0.3), "medium": (5e5, 0.45), "stiff": (1e9, 0.49)}

    def step(names):
        """One step of the named bodies in one place (no contact); returns (info, {name: velocities}), sim."""
        bodies = [Body(name, box_mesh(3), Material(*materials[name], 1000.0), "corotational") for name in names]
        initial = [Initial(Selection(None), "spin", (np.array([0.0, 1.0, 0.0]), 4.0)),
                   Initial(Selection(None), "stretch", (np.array([1.0, 0, 0]), 1.2))]
        sim = fem.Simulation(Scene("side by side", bodies, effects=Effects(), solver=settings, initial=initial))
        x, v, mass = sim.positions(), sim.velocities(), sim.model.mass_np[:, None]
        info = sim.step()
        assert info["converged"]
        after, own = sim.velocities(), {}
        momentum, impulse = mass * v, 0.02 * sim.forces(x)
        residual = momentum + impulse - (assembled_matrix(sim, 1.0, 0.02 ** 2, x) @ after.ravel()).reshape(-1, 3)
        for k, name in enumerate(names):
            rows = slice(sim.model.bodies[k].vertices.start, sim.model.bodies[k].vertices.stop)
            scale = np.sqrt(np.sum(momentum[rows] ** 2) + np.sum(impulse[rows] ** 2))
            assert np.linalg.norm(residual[rows]) / scale <= 1.01e-8, name
            own[name] = after[rows]
        return info, own

    soft_stiff, medium_stiff, soft_medium = step(["soft", "stiff"]), step(["medium", "stiff"]), step(["soft", "medium"])
    np.testing.assert_array_equal(soft_stiff[1]["soft"], soft_medium[1]["soft"])
    np.testing.assert_array_equal(soft_stiff[1]["stiff"], medium_stiff[1]["stiff"])
    np.testing.assert_array_equal(medium_stiff[1]["medium"], soft_medium[1]["medium"])
    assert soft_stiff[0]["solver_iters"] == medium_stiff[0]["solver_iters"]      # the stiff body's own
    assert soft_medium[0]["solver_iters"] < soft_stiff[0]["solver_iters"]          # the medium body's
