"""Effects: pins hold, gravity pulls, the ground stops a falling body."""

import numpy as np
from conftest import box_mesh, make_scene

import fem
from fem.scene import Effects


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
    assert sim.positions()[:, 1].min() >= 0.0
    assert sim.positions()[:, 1].max() < 1.2
