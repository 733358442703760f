"""The trapezoidal rule (Newmark's average acceleration), `solver.integrator = "trapezoidal"`:
its steps equal the textbook Newmark update solved by scipy, it damps nothing (a linear body's
energy and a spinning body's angular momentum are kept), it keeps momentum exactly, it is second
order, and anything that breaks its history restarts it from the acceleration the forces give
at the step's start (no backward Euler step)."""

import math

import numpy as np
import pytest
import scipy.sparse.linalg as spla
from conftest import box_mesh, make_scene
from test_elastic import assembled_matrix
from test_step_promises import angular_momentum, spinning_box

import fem
from app.bench.order import DTS, REFERENCE_DT, observed_order, twisting_bar
from fem.implicit.integrators import DAMPED_TAU, PENALTY_RHO, default_rho
from fem.scene import Effects, SolverSettings


def linear_box(effects, dt):
    scene = make_scene(box_mesh(3), "linear", E=5e4, nu=0.4, effects=effects,
                       solver=SolverSettings(dt=dt, integrator="trapezoidal", tolerance=1e-12, max_iterations=2000,
                                             rho_infinity=1.0))     # damped too: the textbook rule
    sim = fem.Simulation(scene)
    sim.settings.sleep = False
    rng = np.random.default_rng(5)
    X = sim.positions()
    sim.set_state(X + 0.05 * rng.standard_normal(X.shape), rng.standard_normal(X.shape))
    return sim, X


def newmark(M, D, K, f, x, v, X, dt, steps):
    """The textbook average-acceleration Newmark method (beta 1/4, gamma 1/2) on M a + D v + K (x - X) = f,
    started from the equation of motion at t = 0, as the engine: positions after each step."""
    solve = lambda A, b: spla.spsolve(A.tocsc(), b)   # noqa: E731
    a = solve(M, f - D @ v - K @ (x - X))                       # the equation of motion at the start
    out = []
    A = M + dt / 2 * D + dt**2 / 4 * K
    for _ in range(steps):
        a_new = solve(A, f - D @ (v + dt / 2 * a) - K @ (x + dt * v + dt**2 / 4 * a - X))
        x = x + dt * v + dt**2 / 4 * (a + a_new)
        v = v + dt / 2 * (a + a_new)
        a = a_new
        out.append(x)
    return out


def test_its_steps_are_the_textbook_newmark_update(f64):
    """A linear body with gravity and Rayleigh damping, from a random state: 12 steps equal
    scipy's solve of the Newmark update on an independently assembled K."""
    dt, alpha, beta, g = 0.05, 0.3, 0.02, np.array([0.0, -9.81, 0.0])
    sim, X = linear_box(Effects(gravity=tuple(g), alpha=alpha, beta=beta), dt)
    M = assembled_matrix(sim, 1.0, 0.0, X)
    K = assembled_matrix(sim, 0.0, 1.0, X)
    expected = newmark(M, alpha * M + beta * K, K, M @ np.tile(g, len(X)), sim.positions().ravel(),
                       sim.velocities().ravel(), X.ravel(), dt, 12)
    for k, x in enumerate(expected):
        info = sim.step()
        assert info["integrator"] == "trapezoidal", info
        np.testing.assert_allclose(sim.positions().ravel(), x, rtol=0, atol=1e-9)


def test_without_damping_a_linear_body_keeps_its_energy_where_bdf2_loses_some(f64):
    """Kinetic + elastic energy of a free, undamped linear body over 50 steps: the trapezoidal rule
    conserves it for a quadratic energy."""
    kept = {}
    for integrator in ("trapezoidal", "bdf2"):
        sim, _ = linear_box(Effects(), 0.05)
        sim.settings.integrator = integrator
        sim.step()
        start = sim.stats()["total_energy"]
        for _ in range(50):
            sim.step()
        kept[integrator] = sim.stats()["total_energy"] / start
    assert abs(kept["trapezoidal"] - 1) <= 1e-9, kept
    assert kept["bdf2"] < 0.99, kept


def test_momentum_follows_gravity_exactly(f64):
    """An inexact solve (PCG 1e-3) of a spinning corotational body falling freely: its momentum
    after each step is exactly M (v_0 + g t), as with the other integrators."""
    scene = make_scene(box_mesh(3), E=2e5, effects=Effects(gravity=(0.0, -9.81, 0.0)),
                       solver=SolverSettings(dt=0.02, integrator="trapezoidal", tolerance=1e-3))
    sim = fem.Simulation(scene)
    sim.settings.sleep = False
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)
    x = sim.positions()
    sim.set_state(x, np.cross([0.0, 3.0, 1.0], x - x.mean(0)) + [0.5, 0.0, 0.0])
    p0 = (m[:, None] * sim.velocities()).sum(0)
    for k in range(1, 21):
        sim.step()
        p = (m[:, None] * sim.velocities()).sum(0)
        np.testing.assert_allclose(p, p0 + m.sum() * np.array([0.0, -9.81, 0.0]) * 0.02 * k, rtol=0, atol=1e-9)


def test_a_free_spinning_body_keeps_its_angular_momentum(f64):
    """The spinning box of test_step_promises at dt 0.02 s for 2 s, without damping."""
    sim = spinning_box(integrator="trapezoidal")
    start = angular_momentum(sim)[1]
    for _ in range(100):
        sim.step()
    assert angular_momentum(sim)[1] / start >= 0.995        # 0.998 (BDF2: 0.993, backward Euler: 0.77)


def test_an_impulse_or_a_new_dt_restarts_it_from_the_forces_at_its_start(f64):
    """No step of a trapezoidal run is backward Euler's: after an impulse or a new dt, a_n is
    taken from the forces at the step's start (History.fresh), and BDF2's first step after a
    break, or a switch of integrator, is a trapezoidal one."""
    sim = spinning_box(integrator="trapezoidal")
    history = sim.solver.history
    steps = []
    for _ in range(3):
        steps.append((sim.step()["integrator"], history.fresh))
    assert steps == [("trapezoidal", True), ("trapezoidal", False), ("trapezoidal", False)]
    sim.apply_impulse([0], [0.0, 1.0, 0.0])
    assert (sim.step()["integrator"], history.fresh) == ("trapezoidal", True)
    sim.settings.dt = 0.01
    assert (sim.step()["integrator"], history.fresh) == ("trapezoidal", True)
    assert (sim.step()["integrator"], history.fresh) == ("trapezoidal", False)


def test_a_live_switch_of_integrator_restarts_the_history(f64):
    """BDF2's history is no trapezoidal one, nor the other way round: the first step after a switch
    (the window's or a script's `settings.integrator`) starts again, from the forces at its start."""
    sim = spinning_box(integrator="bdf2")
    history = sim.solver.history
    assert [(sim.step()["integrator"], history.fresh) for _ in range(2)] == [("bdf2", True), ("bdf2", False)]
    for integrator in ("trapezoidal", "bdf2", "trapezoidal"):
        sim.settings.integrator = integrator
        assert [(sim.step()["integrator"], history.fresh) for _ in range(2)] == [(integrator, True), (integrator, False)]


def guess_error(dt, t=0.2):
    """The spinning box's last guess for v (Newton.first_iterate, the step's first iterate) at t,
    against the converged step: max |guess - v| / max |v|; and the body's blend then."""
    sim = spinning_box(integrator="trapezoidal")
    sim.settings.dt, sim.settings.tolerance, sim.settings.max_iterations = dt, 1e-10, 5000
    newton, n, seen = sim.solver.newton, sim.model.n_vertices, {}
    first_iterate = newton.first_iterate

    def recorded(*args):
        first_iterate(*args)
        seen["guess"] = newton.guess.to_numpy()[:n]

    newton.first_iterate = recorded
    for _ in range(round(t / dt)):
        sim.step()
    v = sim.velocities()
    return np.abs(seen["guess"] - v).max() / np.abs(v).max(), newton.blend.to_numpy()[0]


def test_its_guess_extrapolates_the_acceleration_where_the_motion_is_resolved(f64):
    """The first iterate blends in the Adams-Bashforth guess from a_n as far as it fitted the
    body's last step: where dt resolves the motion it takes all of it, and the guess is off by
    O(dt^3), where extrapolating the velocity alone is off by O(dt^2)."""
    coarse, _ = guess_error(0.005)
    fine, blend = guess_error(0.0025)
    assert blend >= 0.9, blend                                  # 0.99
    assert coarse / fine >= 6.0, (coarse, fine)                 # 7.8: order 3 (linear: about 4)


@pytest.mark.slow
@pytest.mark.parametrize("step", ["newton", "single"])
def test_it_is_second_order(f64, step):
    """The spinning, twisting bar of app/bench/order.py at dt 0.02, 0.01 and 0.005 s, against
    itself at dt 0.00125 s."""
    measured = observed_order(step=step, integrators=("trapezoidal",))["trapezoidal"]
    assert min(measured["slopes"]) >= 1.8, measured


def damped_bar_errors(rho):
    """The spinning, twisting bar of app/bench/order.py with Rayleigh damping (alpha 0.1, beta 0.02), the
    trapezoidal rule at rho_infinity `rho` (None: the default): its largest vertex error at DTS against
    itself at REFERENCE_DT."""
    def run(dt):
        return twisting_bar(dt, "trapezoidal", effects=Effects(alpha=0.1, beta=0.02), rho_infinity=rho)
    reference = run(REFERENCE_DT)
    return [float(np.abs(run(dt) - reference).max()) for dt in DTS]


@pytest.mark.slow
def test_with_rayleigh_damping_its_default_dissipation_keeps_second_order(f64):
    """With damping the default rho_infinity is exp(-dt / DAMPED_TAU) (integrators.default_rho): the modes
    dt cannot follow decay by e each DAMPED_TAU seconds whatever dt is, and theta - 1/2 falls with dt,
    so the rule stays second order. A fixed rho_infinity of 0.9 (the default before) is first order."""
    assert default_rho(0.02, True, False) == pytest.approx(math.exp(-0.02 / DAMPED_TAU))
    assert default_rho(0.02, False, False) == 1.0 and default_rho(0.001, True, True) == PENALTY_RHO
    by_default, fixed = damped_bar_errors(None), damped_bar_errors(0.9)
    slopes = [math.log2(a / b) for a, b in zip(by_default, by_default[1:])]
    fixed_slopes = [math.log2(a / b) for a, b in zip(fixed, fixed[1:])]
    assert min(slopes) >= 1.8, (slopes, by_default)
    assert max(fixed_slopes) <= 1.6, (fixed_slopes, fixed)       # 1.50, 1.48 over 0.4 s (1.15, 1.07 over 1 s)
    assert by_default[-1] < fixed[-1] / 2.5, (by_default, fixed)


def test_auto_is_the_trapezoidal_rule_but_bdf2_on_the_ground(f64):
    """The default integrator: the trapezoidal rule damps nothing, so a ground's stiff penalty would ring
    (fem/implicit/integrators.py); a scene with a ground steps with BDF2."""
    assert SolverSettings().integrator == "auto"
    for ground, integrator in ((None, "trapezoidal"), (0.0, "bdf2")):
        scene = make_scene(box_mesh(2), effects=Effects(gravity=(0.0, -9.81, 0.0), ground=ground),
                           solver=SolverSettings(dt=0.02), position=(0.0, 0.5, 0.0))
        sim = fem.Simulation(scene)
        assert [sim.step()["integrator"] for _ in range(2)] == [integrator, integrator]
