"""Newton converges on contact (fem/implicit/newton.py, contact.py): a box resting on a slab, a box
sliding on it and a stack at rest meet the gradient's tolerance on their steps, in float32 too,
where a pair's distance is known only to eps |x| and its push to h k m_p b''(d) eps |x| (the
stopping test's round-off floor, Contact.body_noise)."""

from pathlib import Path

import numpy as np
import pytest

import fem
import scenes
from fem.scene import Body, ContactEffect, Effects, Material, Scene, SolverSettings
from scenes.hard_cases import cube


# the shares measured (2026-11-29, 2 cores, after the damping's frame was held in the line search and
# friction majorized for 6 Newton iterations), less a step or two of margin: two_boxes 53 of 57 steps
# after its fall in f32 and in f64 (f32 45 and f64 55 of 57 before). The pile: issue 60's 95 % of its
# first 60 steps (58 of 60 measured in f32 and in f64 on 2026-12-01; see test_a_damped_pile_converges)
TWO_BOXES = {"f32": 0.9, "f64": 0.9}
PILE = 0.95


def box(size, position, name, cells=1):
    mesh = cube(cells=cells, size=size)
    return Body(name, type(mesh)(mesh.vertices + np.asarray(position), mesh.tets, mesh.source),
                Material(1e5, 0.3, 1000.0), "corotational")


def scene(bodies, friction=0.3):
    return Scene("contact", bodies, solver=SolverSettings(dt=0.02),
                 effects=Effects(gravity=(0.0, -9.81, 0.0), ground=0.0, friction=0.5,
                                 contact=ContactEffect(0.01, friction)))


def on_slab():
    """A 0.3 m box 12 mm above a 1 m slab on the ground."""
    return [box((1.0, 0.2, 1.0), (0.0, 0.1, 0.0), "slab", cells=2), box((0.3, 0.3, 0.3), (0.0, 0.362, 0.0), "box")]


def converged_share(sim, steps, falling=0):
    """The share of `steps` steps that converged, after the first `falling` steps: a free fall with
    contact on ends its first step with a rise of the solve's residual that its deformation cannot
    pay for (docs/method.md, section 6), takes the rigid step instead, and says it did not converge."""
    rows = [sim.step() for _ in range(steps)]
    assert all(row["finite"] and row["interpenetrating"] == 0 for row in rows)
    return np.mean([row["converged"] for row in rows[falling:]])


@pytest.mark.parametrize("precision", ["f32", "f64"])
@pytest.mark.parametrize("friction", [0.0, 0.3])
def test_a_box_resting_on_a_slab_converges(precision, friction):
    fem.init("cpu", precision)
    assert converged_share(fem.Simulation(scene(on_slab(), friction)), 60) >= 0.95


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_a_box_sliding_on_a_slab_converges(precision):
    """Landed and settled (its landing, 2 mm, is an impact: f64 left one of its 15 steps at 4e-3),
    then pushed to 1 m/s: it slides, stops (friction 0.3) and rests."""
    fem.init("cpu", precision)
    sim = fem.Simulation(scene(on_slab()))
    converged_share(sim, 15)
    v = sim.velocities()
    v[sim.model.bodies[1].vertices, 0] += 1.0
    sim.set_state(sim.positions(), v)
    assert converged_share(sim, 35) >= 0.95


@pytest.mark.parametrize("precision, share", [("f32", 0.95), ("f64", 1.0)])
def test_every_step_of_a_stack_at_rest_converges(precision, share):
    """Three 0.3 m boxes stacked on the ground, 12 mm apart to start: after the first step (a free
    fall, `converged_share`) they land, settle and rest, every step converged in f64; in f32 60 of 60 steps run alone, but 59 of 60 once after the other
    tests of this file, so at least 95 % there."""
    fem.init("cpu", precision)
    bodies = [box((0.3, 0.3, 0.3), (0.0, 0.15 + 0.312 * k, 0.0), f"box{k}") for k in range(3)]
    assert converged_share(fem.Simulation(scene(bodies)), 60, falling=1) >= share


def scene_file(name):
    return scenes.load_scene(Path(__file__).resolve().parents[1] / name)


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_two_boxes_converge(precision):
    """scenes/two_boxes.toml: the upper box falls (its first steps a free fall, `converged_share`),
    lands on the lower one at 3.7 m/s, bounces and settles."""
    fem.init("cpu", precision)
    assert converged_share(fem.Simulation(scene_file("scenes/two_boxes.toml")), 60, falling=3) >= TWO_BOXES[precision]


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_a_damped_pile_converges(precision):
    """examples/pile.toml (20 boxes, Rayleigh damping, friction 0.3 between them), its first 1.2 s:
    the boxes land and fall onto each other. What kept its steps from converging, each measured:
    the line search's E took the stiffness damping in the frame of each trial iterate, while its
    gradient held that frame (no descent found); friction's Newton model, which has no curvature
    along a slide, sent sliding pairs far past rest, so that the island's one line search halved
    (Newton.solve's majorizer, the first 6 iterations and after each halving); an impact's first
    iterations are cut by the step bound, so most of the steps that stopped at 20 iterations
    converged within 40 (CONTACT_NEWTON); and in f32 sticking friction changes E by less than its
    round-off near the answer, where the trial's slope now decides (fem/implicit/islands.py).
    Unconverged of 60 on 2026-12-01: f64 14 -> 2, f32 25 -> 2."""
    fem.init("cpu", precision)
    assert converged_share(fem.Simulation(scene_file("examples/pile.toml")), 60) >= PILE
