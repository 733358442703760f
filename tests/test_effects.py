"""Effects: pins hold, gravity pulls, the ground stops a falling body, and its friction is
Coulomb's (fem/implicit/effects.py)."""

import numpy as np
import pytest
from conftest import box_mesh, make_scene

import fem
from fem.implicit.effects import CONTACT_STIFFNESS, RECOVERY_SPEED
from fem.scene import Effects, SolverSettings


def test_pinned_vertices_stay_put_and_gravity_pulls_the_rest(f64):
    mesh = box_mesh(2)
    top = np.flatnonzero(np.isclose(mesh.vertices[:, 1], 0.5))
    scene = make_scene(mesh, "corotational", E=1e4, density=100.0, pinned=top,
                       effects=Effects(gravity=(0.0, -9.81, 0.0)))
    sim = fem.Simulation(scene)
    x0 = sim.positions()
    for _ in range(20):
        sim.step()
    x = sim.positions()
    np.testing.assert_array_equal(x[top], x0[top])
    assert (x[~np.isin(np.arange(len(x)), top), 1] < x0[~np.isin(np.arange(len(x)), top), 1]).all()


def test_ground_stops_a_falling_body(f64):
    scene = make_scene(box_mesh(2), "corotational", E=1e4, density=100.0, position=(0, 0.6, 0),
                       effects=Effects(gravity=(0.0, -9.81, 0.0), ground=0.0))
    sim = fem.Simulation(scene)
    for _ in range(100):
        sim.step()
    assert sim.positions()[:, 1].min() >= -1e-3      # the penalty's sag under the body's weight
    assert sim.positions()[:, 1].max() < 1.2


def settled_block(mu, dt=0.01):
    """A stiff 1 m block resting on the ground (its normal forces set) with friction mu."""
    scene = make_scene(box_mesh(2), "corotational", E=1e7, position=(0, 0.5, 0),
                       effects=Effects(gravity=(0.0, -9.81, 0.0), ground=0.0, friction=mu),
                       solver=SolverSettings(dt=dt, tolerance=1e-8, max_iterations=500))
    sim = fem.Simulation(scene)
    for _ in range(30):
        sim.step()
    return sim


@pytest.mark.parametrize("mu", [0.2, 0.5])
def test_a_block_sliding_on_the_ground_slows_at_mu_g(f64, mu):
    """Coulomb friction: a block sliding at 2 m/s decelerates at mu g (analytic), and stops there."""
    sim = settled_block(mu)
    v = sim.velocities()
    v[:, 0] += 2.0
    sim.set_state(sim.positions(), v)
    for _ in range(20):                                # 0.2 s
        sim.step()
    speed = sim.velocities()[:, 0].mean()
    np.testing.assert_allclose(speed, 2.0 - mu * 9.81 * 0.2, rtol=0.03)


def test_a_body_placed_deep_in_the_ground_rises_out_of_it_slowly(f64):
    """A body started 0.3 m into the ground is not shot out by the penalty's stored energy: it
    rises at RECOVERY_SPEED (its plane rises that fast), so its centre rises at most twice as
    fast (the free top rebounds from the bottom's push, as from a piston), and its total energy
    (with the contact's, 3e6 J at the start) never rises."""
    scene = make_scene(box_mesh(2), "corotational", E=1e5, position=(0, 0.2, 0),
                       effects=Effects(gravity=(0.0, -9.81, 0.0), ground=0.0),
                       solver=SolverSettings(dt=0.01, tolerance=1e-6, max_iterations=500))
    sim = fem.Simulation(scene)
    energies, rise = [sim.stats()["total_energy"]], []
    for _ in range(60):
        sim.step()
        energies.append(sim.stats()["total_energy"])
        rise.append(sim.velocities()[:, 1].mean())
    assert max(rise) <= 2 * RECOVERY_SPEED
    assert sim.positions()[:, 1].min() > -1e-3         # out of the ground after 0.6 s
    assert np.diff(energies).max() <= 1e-6 * max(np.abs(energies))



def test_friction_s_smoothing_is_twice_differentiable_and_its_curvatures_are_its_derivatives(f64):
    """friction_shape (IPC's cubic below eps): f0(0) = 0; f1 = f0' and f1' are what it returns
    (central differences); f0, f1 and f1' are continuous at eps (no kink for Newton's model to miss);
    the force never passes Coulomb's (f1 <= 1); and the curvature across the slide is at least the
    one along it, f1 / s >= f1' >= 0 (PSD, and the majorizer the first contact iterations take)."""
    import taichi as ti

    from fem.implicit.effects import FRICTION_SPEED, friction_shape
    from fem.scene import Effects
    eps = FRICTION_SPEED
    assert Effects().stick_speed == eps                   # a scene's default
    s = np.concatenate([np.linspace(1e-6, 3 * eps, 301), eps * (1 + np.array([-1e-7, 1e-7]))])
    out = ti.Vector.field(3, ti.f64, len(s))

    @ti.kernel
    def shape(speeds: ti.types.ndarray()):
        for i in range(out.shape[0]):
            f0, across, along = friction_shape(ti.cast(speeds[i], ti.f64), ti.static(eps))
            out[i] = ti.Vector([f0, across, along], ti.f64)

    def at(speeds):
        shape(np.asarray(speeds, dtype=np.float64))
        return out.to_numpy()[:len(speeds)]

    f0, across, along = at(s).T
    h = 1e-4 * eps
    up, down = at(s + h), at(s - h)
    np.testing.assert_allclose((up[:, 0] - down[:, 0]) / (2 * h), across * s, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose((up[:, 1] * (s + h) - down[:, 1] * (s - h)) / (2 * h), along, rtol=1e-5, atol=1e-3 / eps)
    left, right = at(s[-2:]).T[:, 0], at(s[-2:]).T[:, 1]
    np.testing.assert_allclose(left, right, rtol=1e-5, atol=1e-5 / eps)    # f0, f1 / s, f1' across eps
    assert at([0.0])[0, 0] == 0.0
    assert (across * s <= 1 + 1e-12).all() and (across >= along - 1e-9).all() and (along >= -1e-9).all()
    np.testing.assert_allclose(at([0.0])[0, 1:], [2 / eps, 2 / eps])      # sticking: 2 mu lambda / eps, isotropic


def test_a_step_split_for_a_deep_vertex_measures_the_ground_as_the_scene_dt_does(f64):
    """A step that sinks a vertex too deep is taken again as two of dt / 2 (fem/simulation.py:
    take), whose penalty is four times as stiff (k = CONTACT_STIFFNESS / dt^2). The energy the
    stats and the safeguards measure keeps the scene dt's k (Effects.energy_stiffness): the
    contact energy is numpy's k m / 2 d^2 with the scene's dt, and the total energy never rises.
    Measured with the halves' k, a box dropped at dt 2 s gained 3,750 J in its first step and 170 J
    every other step after."""
    dt = 2.0
    scene = make_scene(box_mesh(2), "corotational", E=1e5, position=(0, 0.3, 0),
                       effects=Effects(gravity=(0.0, -9.81, 0.0), ground=0.0),
                       solver=SolverSettings(dt=dt, tolerance=1e-6, max_iterations=500))
    sim = fem.Simulation(scene)
    energies, rows = [sim.stats()["total_energy"]], []
    for _ in range(6):
        rows.append(sim.step())
        stats = sim.stats()
        energies.append(stats["total_energy"])
        depth = np.minimum(sim.positions()[:, 1], 0.0)
        assert stats["contact_energy"] == pytest.approx(
            0.5 * CONTACT_STIFFNESS / dt ** 2 * np.sum(sim.model.mass_np * depth ** 2), rel=1e-12)
    assert all(row["substeps"] > 1 for row in rows)
    assert np.diff(energies).max() <= 1e-6 * max(np.abs(energies))
