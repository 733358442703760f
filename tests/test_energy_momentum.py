"""The conserving scheme's energy-momentum step (fem/implicit/energy_momentum.py), checked with numpy.

- each step solves the energy-momentum equations, M (v_(n+1) - v_n) = dt (f_algo + M g) with
  x_(n+1) = x_n + dt (v_n + v_(n+1)) / 2, f_algo from numpy's own polar rotations (SVD) and second
  Piola stresses at the step's two ends: the residual recomputed from the states is within the
  tolerance, and f_algo's work over the step is the change of numpy's elastic energy exactly;
- stiff free bodies spinning (E 1e8 to 1e11, nu up to 0.49995, a principal axis and an asymmetric
  top, f32 and f64) are stepped by it: every step converged, none trimmed (no rigid fallback),
  and energy and angular momentum, summed in numpy from the states, kept;
- a stiff float32 body whose Newton stops at its round-off floor takes no rigid step for the error
  that answer leaves (the neighbours of the case above: 10.3 and 11 rad/s, nu 0.45);
- with mass damping (the theta rule) a stiff spinning body's angular momentum decays as the drag
  says, exp(-alpha t), up to the rule's own dissipation, which falls as dt^2; with stiffness
  damping too (no energy-momentum step there) a spinning body, stiff or soft, keeps the spin the
  drag leaves.
"""

import numpy as np
import pytest

import fem
from fem.scene import Body, Effects, Material, Scene, SolverSettings
from scenes.hard_cases import cube
from test_honest_steps import spun
from test_step_promises import angular_momentum


class Reference:
    """The corotated energy of a mesh in numpy: polar rotations from the SVD, per tet
    Psi = W (mu |U - I|^2 + lam / 2 tr(U - I)^2), S = U^-1 sigma(U - I), U = R^T F."""

    def __init__(self, mesh, material):
        X, self.tets = mesh.vertices.astype(np.float64), mesh.tets
        self.Bm = np.linalg.inv(self.edges(X))
        self.W = np.abs(np.linalg.det(self.edges(X))) / 6.0
        E, nu = material.E, material.nu
        self.mu, self.lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))

    def edges(self, x):
        a, b, c, d = (x[self.tets[:, k]] for k in range(4))
        return np.stack([a - d, b - d, c - d], axis=2)

    def stretch(self, x):
        """(F, U) per tet."""
        F = self.edges(x) @ self.Bm
        P, _, Qt = np.linalg.svd(F)
        flip = np.linalg.det(P @ Qt) < 0
        P[flip, :, 2] *= -1
        R = P @ Qt
        U = np.swapaxes(R, 1, 2) @ F
        return F, 0.5 * (U + np.swapaxes(U, 1, 2))

    def energy(self, x):
        """Per tet Psi (J)."""
        _, U = self.stretch(x)
        eps = U - np.eye(3)
        tr = np.trace(eps, axis1=1, axis2=2)
        return self.W * (self.mu * (eps * eps).sum((1, 2)) + 0.5 * self.lam * tr ** 2)

    def second_piola(self, x):
        F, U = self.stretch(x)
        eps = U - np.eye(3)
        sigma = 2 * self.mu * eps + self.lam * np.trace(eps, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        S = np.linalg.solve(U, sigma)
        return F, 0.5 * (S + np.swapaxes(S, 1, 2))

    def algorithmic_forces(self, x0, x1):
        """f_algo (n, 3): Gonzalez's discrete gradient in C = F^T F at the midpoint stress (S0 + S1) / 2."""
        (F0, S0), (F1, S1) = self.second_piola(x0), self.second_piola(x1)
        dC = np.swapaxes(F1, 1, 2) @ F1 - np.swapaxes(F0, 1, 2) @ F0
        S = 0.5 * (S0 + S1)
        size = (dC * dC).sum((1, 2))
        missing = (self.energy(x1) - self.energy(x0)) / self.W - 0.5 * (S * dC).sum((1, 2))
        kappa = np.where(size > 1e-24, 2 * missing / np.maximum(size, 1e-300), 0.0)
        P = 0.5 * (F0 + F1) @ (S + kappa[:, None, None] * dC)
        H = -self.W[:, None, None] * P @ np.swapaxes(self.Bm, 1, 2)
        f = np.zeros_like(x0)
        for k in range(3):
            np.add.at(f, self.tets[:, k], H[:, :, k])
            np.add.at(f, self.tets[:, 3], -H[:, :, k])
        return f


def spinning(E, nu, shape, omega, tolerance=1e-4, effects=None, dt=0.02):
    mesh = cube(2, (0.5, 0.5, 0.5)) if shape == "cube" else cube((3, 2, 2), (0.6, 0.4, 0.3))
    material = Material(E, nu, 1000.0)
    sim = fem.Simulation(Scene("spinning", [Body("box", mesh, material, "corotational")],
                               effects=effects or Effects(), solver=SolverSettings(dt=dt, tolerance=tolerance)))
    spun(sim, omega)
    return sim, Reference(mesh, material)


def total_energy(sim, reference):
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)
    return 0.5 * (m[:, None] * sim.velocities() ** 2).sum() + reference.energy(sim.positions()).sum()


@pytest.mark.parametrize("E, nu", [(1e5, 0.3), (1e8, 0.3), (1e10, 0.45)])
def test_each_step_is_the_energy_momentum_step(f64, E, nu):
    """From the states alone, with numpy's forces: f_algo's work is the change of the elastic
    energy (the discrete gradient's identity, to 1e-9 of the energy's terms), and on every step
    whose positions the projection did not move (`move_positions`), the positions follow the
    trapezoidal rule's x_(n+1) = x_n + dt (v_n + v_(n+1)) / 2 and the residual
    M (v_(n+1) - v_n) - dt f_algo is within the tolerance of |M v_n| + |dt f_algo|."""
    dt, tolerance = 0.02, 1e-4
    sim, reference = spinning(E, nu, "top", (1.0, 10.0, 3.0), tolerance)
    m = sim.model.mass.to_numpy()[:sim.model.n_vertices].astype(np.float64)[:, None]
    guards, moved = sim.solver.safeguards, []
    move = guards.move_positions           # a rise the velocities cannot pay moves the positions (projection.py)
    guards.move_positions = lambda *args: moved.append(1) or move(*args)
    for _ in range(20):
        x0, v0 = sim.positions(), sim.velocities()
        moved.clear()
        info = sim.step()
        x1 = sim.positions()
        assert info["converged"] and not info["energy_limited"], info
        f = reference.algorithmic_forces(x0, x1)
        work, change = (f * (x1 - x0)).sum(), reference.energy(x1).sum() - reference.energy(x0).sum()
        assert abs(work + change) <= 1e-9 * (abs(change) + np.abs(reference.energy(x1)).sum() + 1e-12)
        # the solve's own v_(n+1), before the energy projection scaled its deformation velocities:
        # v^ + h a_(n+1), as the step keeps them (h = dt / 2)
        n = sim.model.n_vertices
        solved = sim.solver.potential.v0.to_numpy()[:n] + 0.5 * dt * sim.solver.history.accel.to_numpy()[:n]
        if moved:                          # (the E 1e10 top on an AVX2 EPYC: 2 of 20 steps, by 1e-8 of |x|)
            continue
        assert np.abs(x1 - x0 - 0.5 * dt * (v0 + solved)).max() <= 1e-12 * np.abs(x1).max()
        residual = np.linalg.norm(m * (solved - v0) - dt * f)
        scale = np.sqrt(((m * v0) ** 2).sum() + ((dt * f) ** 2).sum())
        assert residual <= 1.05 * tolerance * scale, (residual / scale, info["residual"])


@pytest.mark.parametrize("precision, E, nu, shape", [
    ("f64", 1e8, 0.3, "cube"), ("f64", 1e11, 0.3, "cube"), ("f64", 1e8, 0.49995, "cube"),
    ("f64", 1e10, 0.3, "top"), ("f64", 1e11, 0.3, "top"),
    ("f32", 1e8, 0.3, "cube"), ("f32", 1e11, 0.3, "cube"), ("f32", 1e10, 0.3, "top"),
    # on an AMD EPYC with AVX2 only (no AVX-512) from step 58 on every step's Newton iteration stops at a
    # residual of 0.5 to 1 and the body takes rigid steps: issue 61's f32 nearly incompressible bodies, open
    pytest.param("f32", 1e8, 0.4999, "cube", marks=pytest.mark.xfail(
        strict=False, reason="f32 at nu 0.4999 falls back from step 58 on AVX2-only processors (issue 61)")),
    ("f32", 1e9, 0.49, "cube"), ("f32", 1e10, 0.49, "top")])
def test_a_stiff_spinning_body_is_stepped_not_replaced(request, precision, E, nu, shape):
    """A 0.5 m cube spinning at 10 rad/s about a principal axis, or a 0.6 x 0.4 x 0.3 m box at
    (1, 10, 3) rad/s (an asymmetric top), at dt 0.02 s: before the energy-momentum step the
    trapezoidal rule pumped energy into modes dt cannot follow, and the projection replaced 49 of
    50 steps (the cube at E 1e8) and 100 of 100 (the top at E 1e10) by rigid steps that reported
    `converged`. Now every step converges, none is trimmed, and energy (kinetic plus numpy's
    corotated energy) and angular momentum about the centre, from the states, stay those of the
    start over 2 s: to 1e-8 and 1e-12 in float64, 5e-4 and 1e-6 in float32 (where Newton stops at
    what float32 resolves, and the answer's energy error is the solve's own: up to 3.3e-4 on this
    cube and its neighbours, 10 to 11 rad/s and nu 0.45, docs/method.md section 6). Nearly
    incompressible in float32 too, where the volume term's round-off outgrows E's and the floor follows
    lam + 2 mu (Model.body_floor): with a floor in E the cube converged on 0 of 100 steps at nu 0.4999
    and took 100 rigid steps, at E 1e9 and nu 0.49 18 and 17, and the top at E 1e10 and nu 0.49 29."""
    request.getfixturevalue(precision)
    omega = (0.0, 0.0, 10.0) if shape == "cube" else (1.0, 10.0, 3.0)
    sim, reference = spinning(E, nu, shape, omega)
    E0, L0 = total_energy(sim, reference), angular_momentum(sim)
    for _ in range(100):
        info = sim.step()
        assert info["converged"] and not info["energy_limited"] and not info["restarted"], info
    energy, spin = (1e-8, 1e-12) if precision == "f64" else (5e-4, 1e-6)
    assert abs(total_energy(sim, reference) - E0) <= energy * E0
    assert np.linalg.norm(angular_momentum(sim) - L0) <= spin * np.linalg.norm(L0)


@pytest.mark.parametrize("E", [1e8, 1e10])
def test_a_stiff_spinning_body_under_mass_damping_slows_as_the_drag_says(f64, E):
    """Mass damping alpha M is a drag: its torque about a free body's centre is -alpha L, so
    L(t) = L_0 exp(-alpha t) exactly, whatever the body does. A 0.5 m cube spinning at 10 rad/s
    with alpha 0.1 steps by the damped theta rule (rho_infinity exp(-dt / 0.5 s)), whose own
    dissipation of the resolved spin is second order in dt. Before the energy-momentum step took
    the damped rule too, the rule alone pumped the stiff cube's spin into modes dt cannot follow,
    and its dissipation removed them there: it kept 0.21 of L and 0.045 of its energy after 1 s
    at E 1e8, 0.07 and 0.005 at E 1e10 (exp(-0.1) = 0.905). Now every step converges untrimmed, and L(1 s) is off the drag's
    by 0.029 at dt 0.02 s and 0.008 at dt 0.01 s, as much as a soft cube (E 1e5) under the same rule."""
    errors = []
    for dt in (0.02, 0.01):
        sim, _ = spinning(E, 0.3, "cube", (0.0, 10.0, 0.0), effects=Effects(alpha=0.1), dt=dt)
        L0 = np.linalg.norm(angular_momentum(sim))
        for _ in range(round(1.0 / dt)):
            info = sim.step()
            assert info["converged"] and not info["energy_limited"], info
        errors.append(abs(np.linalg.norm(angular_momentum(sim)) / L0 - np.exp(-0.1)))
    assert errors[0] <= 0.035 and errors[1] <= errors[0] / 3.0, errors


@pytest.mark.parametrize("precision, E, alpha", [("f64", 1e8, 0.0), ("f32", 1e8, 0.0), ("f64", 1e8, 0.1),
                                                ("f64", 1e5, 0.0), ("f32", 1e5, 0.0)])
def test_a_spinning_body_under_stiffness_damping_keeps_the_spin_the_drag_leaves(request, precision, E, alpha):
    """Stiffness damping beta K is internal: it turns no body, so a free body's angular momentum
    follows the drag alone, L(t) = L_0 exp(-alpha t). The 0.5 m cube at E 1e8 spinning at 10 rad/s with
    beta 0.01 (the damped theta rule; the energy-momentum step is not taken with stiffness damping)
    kept 0.81 of L after 1 s in f64 and 0.79 in f32 before its spin was the drag's (the rule rang its
    stiff modes, and the energy that pumped was taken out of the spin), and the soft one at E 1e5,
    whose modes dt follows, 0.959 (the rule keeps no L under nonlinear forces). Now at least 0.985
    undragged, and L within 2e-4 of exp(-0.1) with alpha 0.1; the energy, summed in numpy from the
    states, never rises, and no step takes a rigid step."""
    request.getfixturevalue(precision)
    sim, reference = spinning(E, 0.3, "cube", (0.0, 10.0, 0.0), effects=Effects(alpha=alpha, beta=0.01))
    L0, energies = np.linalg.norm(angular_momentum(sim)), [total_energy(sim, reference)]
    for _ in range(50):
        assert not sim.step()["energy_limited"]
        energies.append(total_energy(sim, reference))
    kept = np.linalg.norm(angular_momentum(sim)) / L0
    assert np.diff(energies).max() <= (1e-9 if precision == "f64" else 1e-5) * energies[0], np.diff(energies).max()
    if alpha == 0.0:
        assert kept >= 0.98, kept
    else:
        assert abs(kept - np.exp(-alpha)) <= 1e-3, kept


@pytest.mark.parametrize("E, nu, w", [(1e8, 0.3, 10.3), (1e8, 0.3, 11.0), (1e8, 0.45, 10.0), (1e8, 0.45, 10.5)])
def test_a_float32_stiff_body_at_its_round_off_floor_takes_no_rigid_step(f32, E, nu, w):
    """A stiff float32 body's Newton stops at what float32 resolves (its gradient below the round-off
    floor, potential.gradient_norm), and the energy error that answer leaves is the solve's own error, no
    failed solve (InternalMove.band: under the conserving scheme the band holds the floor's share,
    sqrt(2 floor K_w / m_min)). Before, the band held tol^2 s_b^2 / m_min alone, and the neighbours
    of the case above took rigid steps (in the tests' build): the 0.5 m cube at E 1e8 spinning at
    10.3 and 11 rad/s on 23 and 26 of 100 steps from step 9 on, at nu 0.45 on 21 and 20 (each
    reported unconverged). Now none; energy (numpy's) within 5e-4 (3.3e-4 at most measured) and
    angular momentum within 1e-6 of the start over 2 s."""
    sim, reference = spinning(E, nu, "cube", (0.0, 0.0, w))
    E0, L0 = total_energy(sim, reference), angular_momentum(sim)
    trims = [sim.step()["energy_limited"] for _ in range(100)]
    assert sum(trims) == 0, trims
    assert abs(total_energy(sim, reference) - E0) <= 5e-4 * E0
    assert np.linalg.norm(angular_momentum(sim) - L0) <= 1e-6 * np.linalg.norm(L0)
