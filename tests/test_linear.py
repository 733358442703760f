"""The linear solvers: PCG to the tolerance it reports, an iteration cap reported, Jacobi
iteration reaching PCG's answer."""

import numpy as np
import pytest
from test_solver import spinning

import fem
from fem.scene import Initial, Selection, SolverSettings


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
