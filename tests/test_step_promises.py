"""The step's promises (issue 23), each checked with numbers against an independent reference:

- "converged" means the gradient test passed: a converged step is as close to the exactly
  solved step as its tolerance says;
- a free body spinning without damping keeps its angular momentum with the default step, and
  stiffness damping leaves rigid rotation alone (its stretch is the physical one, from an
  assembled scipy solve of the rotating frame's equilibrium);
- BDF2 is second order.
(test_energy.py: total energy never rises, the ground on.)
"""

import math

import numpy as np
import pytest
import scipy.sparse

import fem
import scenes
from app.bench.order import observed_order
from fem.scene import Effects, SolverSettings
from conftest import box_mesh, make_scene


def spin(sim, omega, axis=1):
    """Set every body spinning rigidly at omega (rad/s) about its centre along `axis`."""
    x = sim.positions()
    v = np.zeros_like(x)
    for body in sim.model.bodies:
        s = body.vertices
        r = x[s] - x[s].mean(axis=0)
        w = np.zeros(3)
        w[axis] = omega
        v[s] = np.cross(w, r)
    sim.set_state(x, v)


def angular_momentum(sim):
    """(3,) total angular momentum about the centre of mass, kg m^2/s."""
    n = sim.model.n_vertices
    m = sim.model.mass.to_numpy()[:n].astype(np.float64)
    x, v = sim.positions(), sim.velocities()
    c = (m[:, None] * x).sum(0) / m.sum()
    return (m[:, None] * np.cross(x - c, v)).sum(0)


def volume_change(X, T, x):
    """sum of the tets' volumes at x over those at X, minus 1."""
    def volumes(p):
        a, b, c, d = (p[T[:, k]] for k in range(4))
        return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6
    return volumes(x).sum() / volumes(X).sum() - 1


# ---------------------------------------------------------------- converged means converged

def wrung_box(nu=0.49):
    """A 320-tet-ish box (cells 4 x 2 x 2... as cube(cells=3): 162 tets) twisted 90 degrees about x."""
    mesh = box_mesh(3)
    X = mesh.vertices
    angle = 0.5 * math.pi * (X[:, 0] - X[:, 0].min()) / np.ptp(X[:, 0]) - 0.25 * math.pi
    c, s = np.cos(angle), np.sin(angle)
    x = X.copy()
    x[:, 1], x[:, 2] = c * X[:, 1] - s * X[:, 2], s * X[:, 1] + c * X[:, 2]
    return mesh, x


@pytest.mark.parametrize("dt", [0.01, 0.02])
def test_a_converged_step_is_within_its_tolerance_of_the_exact_step(f64, dt):
    mesh, twisted = wrung_box()
    exact, loose = (fem.Simulation(make_scene(mesh, nu=0.49, E=1e5), dt=dt, tolerance=tol)
                    for tol in (1e-11, 1e-4))
    exact.settings = SolverSettings(dt=dt, tolerance=1e-11, max_newton=500, max_iterations=2000,
                                    newton_tolerance=1e-14, integrator="backward-euler")
    loose.settings.integrator = "backward-euler"     # one step from rest: its update alone, unprojected
    for sim in (exact, loose):
        sim.set_state(twisted, np.zeros_like(twisted))
    reference = exact.step()
    assert reference["converged"]
    info = loose.step()
    assert info["converged"] == (info["residual"] <= 1e-4), info
    if info["converged"]:
        v, v_exact = loose.velocities(), exact.velocities()
        assert np.linalg.norm(v - v_exact) <= 1e-2 * np.linalg.norm(v_exact)


def test_no_step_reports_converged_above_its_tolerance(f32):
    mesh, twisted = wrung_box()
    sim = fem.Simulation(make_scene(mesh, nu=0.49, E=1e5), dt=0.01, tolerance=1e-4)
    sim.set_state(twisted, np.zeros_like(twisted))
    for _ in range(20):
        info = sim.step()
        assert not info["converged"] or info["residual"] <= 1e-4, info


def test_a_float32_body_far_from_the_origin_converges_as_it_does_at_the_origin(f32):
    """A float32 position x carries a round-off of eps |x|: a body 200 m out has 400 times the strain
    noise of the same body at the origin, and its round-off floors say so (docs/method.md, section 7).
    When they were taken at the body's size, the stiff cube below took 114 Newton iterations over 20
    steps 200 m out and converged on none of them (97 and 3 at 30 m); at the origin, 20 and all 20.
    The far one must converge as often, in about as many iterations, and move as the near one does,
    to what float32 can say 200 m out: its positions' round-off (1.5e-5 m) is a strain of 6e-5 in a
    0.25 m tet, 0.45 J a step in this cube against its spin's 23 J, and the two runs part by about
    0.25 mm a step (4.9 mm, 1 % of its size, after 20; in float64, 6e-6 m)."""
    mesh = box_mesh(n=2, size=0.5)
    runs = {}
    for offset in (0.0, 200.0):
        sim = fem.Simulation(make_scene(mesh, E=1e9, position=(offset, 0.0, 0.0), effects=Effects(gravity=(0, -9.81, 0)),
                                        solver=SolverSettings(dt=0.02)))
        x = sim.positions()
        sim.set_state(x, np.cross([0.3, 0.0, 3.0], x - x.mean(axis=0)))
        infos = [sim.step() for _ in range(20)]
        runs[offset] = (sum(i["newton_iters"] for i in infos), sum(bool(i["converged"]) for i in infos),
                        sim.positions() - (offset, 0.0, 0.0))
    (near_iters, near_converged, near_x), (far_iters, far_converged, far_x) = runs[0.0], runs[200.0]
    assert near_converged == 20 and far_converged == 20, (near_converged, far_converged)
    assert far_iters <= near_iters + 10, (near_iters, far_iters)
    assert np.abs(far_x - near_x).max() <= 0.02 * 0.5, np.abs(far_x - near_x).max()


@pytest.mark.slow
def test_float32_newton_does_not_stop_at_a_round_off_floor_above_the_round_off(f32):
    """fertility, 1 s of the default (trapezoidal) Newton step at PCG 1e-4 in float32, against the same
    scheme solved to 1e-8 in float64. Newton's gradient floor (GRADIENT_ROUNDOFF eps h E L^2) was at
    30, 60 to 600 times float32's measured noise: the steps stopped there, still converged by that
    test, 2.3e-4 of the scene's size from the answer after 50 steps; at 10, 0.72e-4 (float64 at 1e-4:
    0.04e-4)."""
    scene = scenes.load_scene("fertility")
    positions = {}
    for precision, tolerance in (("f64", 1e-8), ("f32", 1e-4)):
        fem.init("cpu", precision)
        sim = fem.Simulation(scene, step="newton", integrator="trapezoidal", tolerance=tolerance)
        infos = [sim.step() for _ in range(50)]
        positions[precision] = sim.positions()
        if precision == "f32":
            assert all(i["converged"] for i in infos)
    exact = positions["f64"]
    size = np.linalg.norm(np.ptp(exact, axis=0))
    distance = np.sqrt(((positions["f32"] - exact) ** 2).sum(axis=1).mean()) / size
    assert distance <= 1.2e-4, distance


# ---------------------------------------------------------------- rigid rotation is left alone

def spinning_box(alpha=0.0, beta=0.0, integrator=None):
    scene = make_scene(box_mesh(3), E=2e5, nu=0.3, effects=Effects(alpha=alpha, beta=beta),
                       solver=SolverSettings(dt=0.02))
    if integrator is not None:
        scene.solver.integrator = integrator
    sim = fem.Simulation(scene)
    sim.settings.sleep = False
    spin(sim, 3.0)
    return sim


def centrifugal_stretch(sim, omega):
    """J - 1 of the body spinning steadily at omega about y: K u = omega^2 M P (X - c), linear
    elasticity assembled with scipy (rigid modes removed by the solve's minimum norm)."""
    from test_elastic import reference_Ke
    model = sim.model
    n = model.n_vertices
    X = model.rest_positions.to_numpy()[:n].astype(np.float64)
    T = model.tets.to_numpy()[:model.n_tets]
    E, nu = 2e5, 0.3
    rows, cols, vals = [], [], []
    for t in T:
        Ke = reference_Ke(X[t], E, nu)
        idx = (3 * t[:, None] + np.arange(3)).ravel()
        rows.append(np.repeat(idx, 12))
        cols.append(np.tile(idx, 12))
        vals.append(Ke.ravel())
    K = scipy.sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(3 * n, 3 * n)).toarray()
    m = model.mass.to_numpy()[:n].astype(np.float64)
    r = X - (m[:, None] * X).sum(0) / m.sum()
    r[:, 1] = 0.0
    f = (omega ** 2 * m[:, None] * r).ravel()
    u = np.linalg.lstsq(K, f, rcond=1e-10)[0].reshape(n, 3)
    return volume_change(X, T, X + u)


def test_a_free_spinning_body_keeps_its_angular_momentum_with_bdf2(f64):
    kept = {}
    for integrator in ("backward-euler", "bdf2"):
        sim = spinning_box(integrator=integrator)
        start = angular_momentum(sim)[1]
        for _ in range(100):                      # 2 s
            sim.step()
        kept[integrator] = angular_momentum(sim)[1] / start
    assert kept["bdf2"] >= 0.99, kept
    assert kept["backward-euler"] < kept["bdf2"]  # backward Euler's own damping: first order


def test_stiffness_damping_leaves_rigid_rotation_alone(f64):
    sim = spinning_box(beta=0.1, integrator="bdf2")
    start = angular_momentum(sim)[1]
    for _ in range(100):
        sim.step()
    assert angular_momentum(sim)[1] / start >= 0.98
    n = sim.model.n_vertices
    X = sim.model.rest_positions.to_numpy()[:n].astype(np.float64)
    J = volume_change(X, sim.model.tets.to_numpy()[:sim.model.n_tets], sim.positions())
    physical = centrifugal_stretch(sim, 3.0)
    assert physical > 0
    # BDF2's start now takes its history from the forces (no trapezoidal first step): the stretch
    # then swings between 0.85 and 0.91 of the static one over 1 to 5 s (BDF2's and beta's damping
    # of a strained spinning body, whose turn K(R) does not see as rigid)
    assert abs(J - physical) <= 0.15 * physical


# ---------------------------------------------------------------- BDF2's order

@pytest.mark.slow
def test_bdf2_is_second_order_and_backward_euler_first(f64):
    """The spinning, twisting bar of app/bench/order.py (the lab sheet's figure) at dt 0.02, 0.01
    and 0.005 s, against each integrator at dt 0.00125 s."""
    measured = observed_order()
    for integrator, order in (("bdf2", 1.8), ("backward-euler", 0.8)):
        slopes = measured[integrator]["slopes"]
        assert min(slopes) >= order, (integrator, measured[integrator])


@pytest.mark.slow
def test_bdf2_one_solve_step_is_second_order_too(f64):
    """The one-solve step linearises once, at its first iterate: BDF2's starts from the
    extrapolated velocity (O(dt^3) from the answer in position), so it keeps second order;
    from x^ (v = 0) it was first order (slopes 0.94, 0.97)."""
    measured = observed_order(step="single", integrators=("bdf2",))["bdf2"]
    assert min(measured["slopes"]) >= 1.8, measured


# ---------------------------------------------------------------- a live switch of model

def test_after_switching_an_inflated_linear_body_to_corotational_energy_never_rises(f32):
    """The window's `c` on a strongly inflated linear body: the elastic energy jumps with the
    model (the inflated shape really is stretched), but from the switch on every step is a
    minimisation with the energy safeguard: total energy never rises (f32: 1e-3 of its largest).
    (Its tets still turn inside out on the way back from a 40-fold inflation: not yet avoided.)"""
    sim = fem.Simulation(make_scene(box_mesh(3), "linear", E=1e4, nu=0.3, solver=SolverSettings(dt=0.02)))
    sim.settings.sleep = False
    spin(sim, 8.0)
    for _ in range(40):                           # linear FEM inflates a spinning body
        sim.step()
    assert sim.stats()["volume_ratio"][0] > 1.2
    sim.set_method("corotational")
    energies = [sim.stats()["total_energy"]]
    for _ in range(50):
        assert sim.step()["finite"]
        energies.append(sim.stats()["total_energy"])
    rises = np.diff(energies)
    assert rises.max() <= 1e-3 * max(energies), rises.max()


def test_switching_epcot_early_snaps_back_as_the_lab_sheet_says(f32):
    """docs/experiments.md, section 2: `c` pressed after 1.5 s on the linear epcot (1.5 times its
    volume) snaps it back within about 0.15 s (7 steps of 0.02 s) and it stays there, volume
    within 2 %; the switch itself raises the elastic energy (the same shape, counted in full)."""
    sim = fem.Simulation(scenes.load_scene("epcot"), method="linear")
    sim.settings.sleep = False
    for _ in range(75):                           # 1.5 s
        sim.step()
    before = sim.stats()
    assert 1.3 < before["volume_ratio"][0] < 1.7, before["volume_ratio"]
    sim.set_method("corotational")
    ratios, energies = [], [before["total_energy"]]
    for _ in range(30):
        assert sim.step()["finite"]
        now = sim.stats()
        ratios.append(now["volume_ratio"][0])
        energies.append(now["total_energy"])
    assert energies[1] > 10 * energies[0]         # the switch's jump: the inflated shape's true energy
    assert all(abs(r - 1) < 0.02 for r in ratios[7:]), ratios
    assert max(np.diff(energies[1:])) <= 1e-3 * max(energies)
