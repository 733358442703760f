"""Friction as Coulomb says (fem/implicit/friction.py between bodies, fem/implicit/effects.py on the
ground): a block given 1 m/s stops after v^2 / (2 mu g) in v / (mu g), and stays there; a block on
a support tilted by theta holds below tan(theta) = mu and slides above, at g (sin - mu cos)."""

import math
from dataclasses import replace

import numpy as np
import pytest

import fem
from fem.scene import Body, ContactEffect, Effects, Material, Scene, SolverSettings
from scenes.hard_cases import cube

MU, G, SPEED = 0.3, 9.81, 1.0


def box(cells, size, position, name):
    mesh = cube(cells=cells, size=size)
    return Body(name, type(mesh)(mesh.vertices + np.asarray(position), mesh.tets, mesh.source),
                Material(1e6, 0.3, 1000.0), "corotational")


def block_scene(support, dt, gravity=(0.0, -G, 0.0)):
    """A 0.3 m block (one cell) on a 3 m slab lying on the ground (contact friction MU; the ground's,
    0.5, holds the slab), or on the ground itself (its friction MU), 12 mm above it to start."""
    if support == "slab":
        bodies = [box(2, (3.0, 0.2, 1.0), (0.5, 0.1, 0.0), "slab"), box(1, (0.3, 0.3, 0.3), (-0.5, 0.362, 0.0), "block")]
        effects = Effects(gravity=gravity, ground=0.0, friction=0.5, contact=ContactEffect(0.01, MU))
    else:
        bodies = [box(1, (0.3, 0.3, 0.3), (-0.5, 0.162, 0.0), "block")]
        effects = Effects(gravity=gravity, ground=0.0, friction=MU)
    return fem.Simulation(Scene("block", bodies, solver=SolverSettings(dt=dt), effects=effects))


def mean_x(sim):
    block = sim.model.bodies[-1].vertices
    return sim.positions()[block, 0].mean(), sim.velocities()[block, 0].mean()


@pytest.mark.parametrize("support", ["slab", "ground"])
@pytest.mark.parametrize("dt", [0.01, 0.02])
def test_a_sliding_block_stops_where_and_when_coulomb_says(f64, support, dt):
    """Settled for 0.3 s, then given 1 m/s: the block stops within 5 % of v^2 / (2 mu g) = 0.170 m
    and v / (mu g) = 0.340 s (the time its mean velocity crosses 0, interpolated within the step),
    and after stopping moves back by less than a millimetre (static friction holds it)."""
    sim = block_scene(support, dt)
    for _ in range(round(0.3 / dt)):
        sim.step()
    v = sim.velocities()
    v[sim.model.bodies[-1].vertices, 0] += SPEED
    sim.set_state(sim.positions(), v)
    x0 = mean_x(sim)[0]
    xs, vs = [], []
    for _ in range(round(0.7 / dt)):
        sim.step()
        x, u = mean_x(sim)
        xs.append(x - x0)
        vs.append(u)
    k = next(k for k, u in enumerate(vs) if u <= 0.0)
    stop_time = dt * (k + vs[k - 1] / (vs[k - 1] - vs[k]))
    assert max(xs) == pytest.approx(SPEED ** 2 / (2 * MU * G), rel=0.05)
    assert stop_time == pytest.approx(SPEED / (MU * G), rel=0.05)
    assert max(xs) - xs[-1] < 1e-3
    assert abs(vs[-1]) < 0.01


@pytest.mark.parametrize("support", ["slab", "ground"])
@pytest.mark.parametrize("tan_theta", [0.2, 0.4])
def test_a_block_on_a_tilted_support_holds_below_mu_and_slides_above(f64, support, tan_theta):
    """Gravity tilted by theta (the support tilted the other way): below tan(theta) = mu the block
    holds (it creeps below friction's smoothing speed, 1 mm/s, so less than a millimetre in 0.6 s);
    above, it slides down at g (sin(theta) - mu cos(theta)) (within 5 %)."""
    theta = math.atan(tan_theta)
    dt = 0.01
    sim = block_scene(support, dt, gravity=(G * math.sin(theta), -G * math.cos(theta), 0.0))
    for _ in range(40):                                      # it lands (sliding as it falls) and settles
        sim.step()
    x0, v0 = mean_x(sim)
    for _ in range(60):
        sim.step()
    x1, v1 = mean_x(sim)
    if tan_theta < MU:
        assert x1 - x0 < 1e-3
    else:
        assert (v1 - v0) / 0.6 == pytest.approx(G * (math.sin(theta) - MU * math.cos(theta)), rel=0.05)


def with_stick_speed(sim, speed):
    """The same simulation with friction's stick speed (`[effects] stick_speed`) set to `speed`."""
    return fem.Simulation(replace(sim.scene, effects=replace(sim.scene.effects, stick_speed=speed)))


@pytest.mark.parametrize("support", ["slab", "ground"])
def test_the_stick_speed_bounds_the_creep_of_a_held_block(f64, support):
    """`[effects] stick_speed` is IPC's eps_v: friction holds below it, so a block on a support tilted
    below tan(theta) = mu creeps, but never faster: at 1 mm/s (the default) and 10 mm/s it moves less
    than the stick speed times the 0.6 s watched, and the faster stick speed lets it creep further."""
    theta = math.atan(0.2)
    creep = {}
    for speed in (1e-3, 1e-2):
        sim = with_stick_speed(block_scene(support, 0.01, gravity=(G * math.sin(theta), -G * math.cos(theta), 0.0)),
                               speed)
        for _ in range(40):
            sim.step()
        x0, _ = mean_x(sim)
        for _ in range(60):
            sim.step()
        x1, v1 = mean_x(sim)
        assert 0.0 <= x1 - x0 < speed * 0.6 and abs(v1) <= speed
        creep[speed] = x1 - x0
    assert creep[1e-2] > creep[1e-3], creep


def test_a_faster_stick_speed_takes_fewer_newton_iterations(f64):
    """What the stick speed buys: friction's curvature while it sticks is 2 mu lambda / eps, so a larger
    eps is a better conditioned step. The block sliding on the slab to rest (as above, dt 0.02 s):
    fewer Newton iterations at 10 mm/s than at 1 mm/s, and it still stops where Coulomb says (5 %)."""
    iterations = {}
    for speed in (1e-3, 1e-2):
        sim = with_stick_speed(block_scene("slab", 0.02), speed)
        for _ in range(15):
            sim.step()
        v = sim.velocities()
        v[sim.model.bodies[-1].vertices, 0] += SPEED
        sim.set_state(sim.positions(), v)
        x0 = mean_x(sim)[0]
        iterations[speed] = sum(sim.step()["newton_iters"] for _ in range(35))
        assert mean_x(sim)[0] - x0 == pytest.approx(SPEED ** 2 / (2 * MU * G), rel=0.05)
    assert iterations[1e-2] < iterations[1e-3], iterations
