"""Newton's iteration: exact on linear bodies, a line search that only goes down, per-body
stopping, no work for a body at rest, and a first guess extrapolated from the last step."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse.linalg as spla
from conftest import box_mesh, make_scene
from test_elastic import assembled_matrix
from test_solver import spinning

import fem
import fem.implicit.newton as newton_module
from fem.scene import Body, Effects, Initial, Material, Scene, Selection, SolverSettings, place_mesh
from scenes import load_scene


def test_one_newton_iteration_on_a_linear_body_is_the_exact_linear_solve(f64):
    """(M + dt D + dt^2 K) v = M v_n - dt K (x_n - X) + dt M g, D = alpha M + beta K,
    solved by scipy on an independently assembled K."""
    dt, alpha, beta, g = 0.05, 0.3, 0.02, np.array([0.0, -9.81, 0.0])
    effects = Effects(gravity=tuple(g), alpha=alpha, beta=beta)
    sim = fem.Simulation(make_scene(box_mesh(3), "linear", E=5e4, nu=0.4, effects=effects,
                                    solver=SolverSettings(dt=dt, tolerance=1e-12, max_iterations=2000,
                                                          integrator="backward-euler")))
    rng = np.random.default_rng(3)
    X = sim.positions()
    x0, v0 = X + 0.05 * rng.standard_normal(X.shape), rng.standard_normal(X.shape)
    sim.set_state(x0, v0)

    info = sim.step()

    M = assembled_matrix(sim, 1.0, 0.0, X)
    K = assembled_matrix(sim, 0.0, 1.0, X)
    A = (1 + dt * alpha) * M + (dt * beta + dt**2) * K
    rhs = M @ v0.ravel() - dt * K @ (x0 - X).ravel() + dt * M @ np.tile(g, len(X))
    v = spla.spsolve(A.tocsc(), rhs).reshape(-1, 3)
    # one iteration solves it; a second may follow where the answer's own scale is smaller than
    # the start's (the convergence test is taken at the answer)
    assert info["newton_iters"] <= 2 and info["line_search_steps"] == 0
    np.testing.assert_allclose(sim.velocities(), v, rtol=0, atol=1e-9 * np.abs(v).max())
    np.testing.assert_allclose(sim.positions(), x0 + dt * v, rtol=0, atol=1e-9 * np.abs(v).max() * dt + 1e-14)


def spinning_incompressible(method="corotational", nu=0.4999, omega=15.0, dt=0.5):
    """The former expected failure: a near-incompressible cube spinning fast at a large dt."""
    body = Body("rubber", box_mesh(2), Material(1e4, nu, 1000.0), method)
    spin = Initial(Selection(0), "spin", (np.array([0.0, 0.0, 1.0]), omega))
    return Scene("spin", [body], effects=Effects(alpha=0.1, beta=0.1), initial=[spin],
                 solver=SolverSettings(dt=dt, tolerance=1e-6))


def test_the_line_search_never_accepts_an_increase_of_E(f64):
    """E is evaluated at the start iterate and at every trial; each accepted trial's E is at
    most the accepted E its search started from (Armijo), on a case that needs halvings. Its
    stiffness damping outweighs its inertia at this dt, so each search holds the damping's frame
    (IncrementalPotential.holds_frame): a trial's E is in the frame of the iterate the search
    started from, and that iterate's accepted E is in its own frame, the same one."""
    sim = fem.Simulation(spinning_incompressible())
    solver, potential, newton = sim.solver, sim.solver.potential, sim.solver.newton
    assert potential.holds_frame
    trial, settle, step = newton.evaluate_trial, newton.settle, solver.step
    paths, last, slack = [], [], []   # per step: (the search's start E, its accepted trial's E)

    def E():
        return potential.body_E.to_numpy()[:1]            # E_b of the scene's one body

    def logged_trial(*args):
        out = trial(*args)
        last[:] = [E()]
        return out

    def logged_settle(*args):
        start = newton.body_E_accepted.to_numpy()[:1]     # the accepted E this search started from
        paths[-1].append((start, last[0]))                # the trial just evaluated is the one accepted
        return settle(*args)

    def logged_step(*args, **kwargs):
        paths.append([])
        out = step(*args, **kwargs)
        slack.append(newton.body_resolution.to_numpy()[:1])
        return out

    newton.evaluate_trial, newton.settle, solver.step = logged_trial, logged_settle, logged_step
    halvings = sum(sim.step()["line_search_steps"] for _ in range(12))
    assert halvings > 0, "the case must exercise the line search"
    assert sum(len(path) for path in paths) >= len(paths)      # Newton iterations were accepted
    # a change within the round-off of E_b (body_resolution, set at the step's first iterate) is noise
    for path, noise in zip(paths, slack):
        assert all(b <= a + noise for a, b in path), (path, noise)   # noqa: (1,) arrays


def two_bodies(quiet_only=False, tolerance=1e-4, newton_tolerance=1e-3):
    """A quiet body squashed to 80 % and released, and (unless quiet_only) beside it a
    body whose corner is hit at 1e5 m/s."""
    quiet = Body("quiet", box_mesh(2), Material(1e4, 0.3, 1000.0), "corotational")
    squash = Initial(Selection(0), "squash", (np.array([0.0, 1.0, 0.0]), 0.8))
    bodies, initial = [quiet], [squash]
    if not quiet_only:
        bodies.append(Body("hit", place_mesh(box_mesh(2), (5.0, 0.0, 0.0)), Material(1e4, 0.3, 1000.0),
                           "corotational"))
        initial.append(Initial(Selection(1, vertices=np.array([0])), "velocity", (np.array([1e5, 0.0, 0.0]),)))
    return Scene("pair", bodies, initial=initial,
                 solver=SolverSettings(dt=0.02, tolerance=tolerance, newton_tolerance=newton_tolerance))


def quiet_body_offset(**tolerances):
    """(how far the quiet body ends from where it ends alone, how far it moved), m, after 5 steps."""
    pair, alone = fem.Simulation(two_bodies(**tolerances)), fem.Simulation(two_bodies(True, **tolerances))
    start = alone.positions()
    for _ in range(5):
        pair.step()
        alone.step()
    n = alone.model.n_vertices
    return np.abs(pair.positions()[:n] - alone.positions()).max(), np.abs(alone.positions() - start).max()


def test_a_quiet_body_is_solved_as_well_beside_a_huge_impulse(f64):
    """Per-body stopping and line search: the hit body's huge residual and energy set neither
    the scale nor the resolution for its quiet neighbour, which ends where it ends alone."""
    offset, moved = quiet_body_offset()
    assert moved > 1e-2
    # Within 0.1 % of its motion (measured 0.0075 %): each body has its own line search and
    # stopping test. With one line search on the scene's E, whose float64 sum cannot resolve
    # the quiet body's share beside the hit body's energy, it ended 0.7 to 1 % off; a quiet
    # body left unsolved would be off by its whole motion.
    assert offset < 1e-3 * moved


def test_beside_a_huge_impulse_a_quiet_body_converges_as_far_as_it_is_asked(f64):
    """What is left between the pair and the body alone is each run's own tolerance: asked for
    1e-8 (gradient and velocity change), they agree to 1e-6 of the motion (measured 4e-8;
    7.5e-5 at the defaults, 1e-4 and 1e-3). Nothing of the hit body leaks into the quiet one."""
    offset, moved = quiet_body_offset(tolerance=1e-8, newton_tolerance=1e-8)
    assert offset < 1e-6 * moved


def test_a_body_at_rest_costs_no_solver_iterations(f64):
    sim = fem.Simulation(make_scene(box_mesh(3), "corotational", E=1e6, nu=0.45,
                                    solver=SolverSettings(dt=0.02, tolerance=1e-4)))
    infos = [sim.step() for _ in range(5)]
    assert [i["solver_iters"] for i in infos] == [0] * 5
    assert all(i["converged"] for i in infos)


def test_the_coursework_cylinder_at_rest_costs_no_solver_iterations(cggs):
    fem.init("cpu", "f32")
    sim = fem.Simulation(load_scene(cggs / "cylinder-scene.txt"))
    infos = [sim.step() for _ in range(5)]
    fem.init("cpu", "f64")
    # In f32 the trapezoidal rule's a_n, taken from the forces at the first step's start, carries
    # their round-off into the second step's guess, which one CG iteration corrects (dropping
    # a_n's elastic part below the round-off floor cost a stiff f32 bar 0.8 % of its fall):
    # at most three (two with the damped default rho_infinity exp(-dt / 0.5 s), which carries more
    # of a_n into the guess than 0.9 did; three since float32's gradient floor is 10 eps h E L^2, not
    # 30: the solve takes out more of that round-off), and none from the third step on
    iters = [i["solver_iters"] for i in infos]
    assert iters[0] == 0 and iters[1] <= 3 and iters[2:] == [0] * 3, iters


def test_the_first_guess_extrapolates_the_last_steps_change(f64):
    """Each solve starts from v_n + (dt / dt_prev)(v_n - v_(n-1)). Falling freely, a body's velocity changes by
    g dt every step: from the second step on that guess is the answer and PCG has nothing left
    to do, where a start from v_n needs iterations. A new state (set_state) starts from v_n
    alone; a rejected step leaves no NaN in the guess."""
    g, dt = np.array([0.0, -9.81, 0.0]), 0.02
    runs = {}
    for forget in (False, True):
        scene = spinning("corotational", omega=0.0, effects=Effects(gravity=tuple(g)),
                         solver=SolverSettings(dt=dt, tolerance=1e-6, step="single",
                                               integrator="backward-euler"))   # the fall below is its
        sim = fem.Simulation(scene)
        x0, iterations = sim.positions(), []
        for _ in range(10):
            if forget:
                sim.set_state(sim.positions(), sim.velocities())   # the same state, no memory
            iterations.append(sim.step()["solver_iters"])
        runs[forget] = sim, iterations
    (sim, extrapolated), (_, from_vn) = runs[False], runs[True]
    assert extrapolated[0] == from_vn[0] > 0             # the first step has no last step
    # at most one iteration: the guess carries the last solve's own error (the tolerance)
    assert max(extrapolated[1:]) <= 1 and min(from_vn[1:]) >= 10
    fallen = dt * dt * g * 10 * 11 / 2                    # backward Euler: v_k = k dt g, x_n = x_0 + dt sum v_k
    np.testing.assert_allclose(sim.positions(), x0 + fallen, atol=1e-6)       # 22 mm fallen

    sim.settings = replace(sim.settings, dt=dt / 2)      # the change scales with dt: g dt / 2 now
    assert sim.step()["solver_iters"] <= 1

    sim.apply_impulse([3], (np.nan, 0.0, 0.0))           # an impulse that breaks the step
    assert not sim.step()["finite"]
    assert np.isfinite(sim.solver.newton.guess.to_numpy()).all()


@pytest.mark.parametrize("step", ["newton", "single"])
@pytest.mark.parametrize("method", ["linear", "corotational"])
def test_a_guess_that_meets_the_tolerance_is_a_converged_step(f64, step, method):
    """A free body gliding at 3 m/s: BDF2's guess v_n + (v_n - v_(n-1)) is the answer itself,
    so its steps take no CG iteration and report converged (the rule that v = 0 is no answer
    for a moving body applies to v = 0 alone). A guess that is not the answer is solved."""
    sim = fem.Simulation(make_scene(box_mesh(2), method, E=1e4, nu=0.3,
                                    solver=SolverSettings(dt=0.01, integrator="bdf2", step=step)))
    sim.settings.sleep = False
    X = sim.positions()
    sim.set_state(X, np.tile([3.0, 0.0, 0.0], (len(X), 1)))
    infos = [sim.step() for _ in range(5)]
    assert infos[0]["integrator"] == "bdf2"          # BDF2's start: its history from the start's forces
    assert all(i["converged"] for i in infos), infos
    assert all(i["solver_iters"] == 0 for i in infos[1:]), infos
    assert np.allclose(sim.velocities(), [3.0, 0.0, 0.0], atol=1e-9)
    x, v = sim.positions(), sim.velocities()
    v[:4] += 1.0                                  # a kick: the next guess is off
    sim.set_state(x, v)
    sim.step()
    info = sim.step()                             # BDF2 again, from a guess that is not the answer
    assert info["integrator"] == "bdf2" and info["converged"] and info["solver_iters"] > 0, info
