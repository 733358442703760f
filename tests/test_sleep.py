"""Bodies at rest sleep: steps cost nothing for them, and waking changes nothing but the cost."""

from dataclasses import replace

import numpy as np
import taichi as ti

import fem
from conftest import box_mesh, make_scene
from fem.scene import Effects, Initial, Selection, SolverSettings

DAMPED = Effects(alpha=2.0, beta=0.05)
SETTINGS = SolverSettings(dt=0.02, tolerance=1e-6)


def settling_scene(sleep=True, effects=DAMPED, bodies=1):
    """Damped cubes, stretched 10 % and let go: they ring down and come to rest."""
    scene = make_scene(box_mesh(3), effects=effects, solver=replace(SETTINGS, sleep=sleep))
    for k in range(1, bodies):
        other = make_scene(box_mesh(3), position=(2.0 * k, 0, 0)).bodies[0]
        scene.bodies.append(replace(other, name=f"box{k}"))
    scene.initial = [Initial(Selection(b), "stretch", (np.array([0.0, 1.0, 0.0]), 1.1))
                     for b in range(len(scene.bodies))]
    return scene


def run_until_asleep(sim, body=0, steps=600):
    for k in range(steps):
        sim.step()
        if sim.asleep[body]:
            return k + 1
    raise AssertionError(f"body {body} never fell asleep in {steps} steps")


def test_a_body_at_rest_falls_asleep_and_its_steps_launch_no_kernel():
    fem.init("cpu", "f32")
    ti.init(arch=ti.cpu, default_fp=ti.f32, kernel_profiler=True, log_level=ti.ERROR)
    sim = fem.Simulation(settling_scene())
    run_until_asleep(sim)
    x, v = sim.positions(), sim.velocities()
    assert not v.any()                                  # asleep: exactly at rest
    ti.sync()
    ti.profiler.clear_kernel_profiler_info()
    infos = [sim.step() for _ in range(5)]
    ti.sync()
    assert ti.lang.impl.get_runtime().prog.get_kernel_profiler_records() == []
    assert all(i["solver_iters"] == 0 and i["asleep"] == [True] for i in infos)
    assert np.array_equal(sim.positions(), x) and sim.t > 0
    fem.init("cpu", "f32")


def positions_after_a_push(sleep, push_at, steps_after=30):
    sim = fem.Simulation(settling_scene(sleep))
    for _ in range(push_at):
        sim.step()
    slept = sim.asleep[0]
    before = sim.positions()
    sim.apply_impulse(np.arange(9), (0.5, 0.2, 0.0))    # a click's impulse on a few vertices
    for _ in range(steps_after):
        sim.step()
    return slept, before, sim.positions()


def test_a_sleeping_body_woken_by_an_impulse_moves_as_if_it_had_never_slept():
    fem.init("cpu", "f32")
    probe = fem.Simulation(settling_scene())
    run_until_asleep(probe)
    push_at = probe.steps + 20
    slept, before, woken = positions_after_a_push(True, push_at)
    awake, before_awake, never_slept = positions_after_a_push(False, push_at)
    assert slept and not awake
    motion = np.abs(never_slept - before_awake).max()
    assert motion > 1e-3
    assert np.abs(woken - never_slept).max() < 1e-3 * motion


def test_a_quiet_body_sleeps_beside_a_moving_one_without_changing_it():
    fem.init("cpu", "f32")
    runs = {}
    for sleep in (True, False):
        scene = settling_scene(sleep, bodies=2)
        # damped (alpha = 2/s), the spin dies out as exp(-2 t): still turning after 4 s, when box 0 sleeps
        scene.initial.append(Initial(Selection(1), "spin", (np.array([0.0, 0.0, 1.0]), 2.0)))
        sim = fem.Simulation(scene)
        asleep = []
        for _ in range(200):
            asleep.append(sim.step()["asleep"])
        spinning = sim.model.bodies[1].vertices
        runs[sleep] = sim.positions(), asleep, spinning, sim.model.rest_positions_np[spinning]
    (x, asleep, spinning, rest), (x_ref, _, _, _) = runs[True], runs[False]
    assert asleep[-1] == [True, False]
    motion = np.abs(x_ref[spinning] - rest).max()
    assert np.abs(x[spinning] - x_ref[spinning]).max() < 1e-3 * motion


def test_edits_wake_a_body_and_a_body_resting_on_the_ground_sleeps_on_it():
    fem.init("cpu", "f32")
    ground = Effects(gravity=(0.0, -9.81, 0.0), ground=0.0, alpha=2.0, beta=0.05)
    scene = make_scene(box_mesh(3), effects=ground, solver=SETTINGS, position=(0, 0.05, 0))
    sim = fem.Simulation(scene)
    run_until_asleep(sim, steps=1500)      # ~450 steps: friction holds it (creep below FRICTION_SPEED)
    assert sim.positions()[:, 1].min() >= -1e-3          # the penalty's sag under the body's weight
    sim.set_material(0, 1e5, 0.3)          # stiffer: the squashed body (E 1e4 Pa, 1 m) springs back up
    assert sim.asleep == [False]
    run_until_asleep(sim, steps=1500)
    sim.set_method("linear")
    assert sim.asleep == [False]
    run_until_asleep(sim, steps=1500)
    sim.set_state(sim.positions(), sim.velocities())
    assert sim.asleep == [False]


def test_sleeping_is_a_scene_setting_that_set_can_turn_off():
    import scenes

    assert scenes.load_scene("cube86").solver.sleep is True
    assert scenes.load_scene("cube86", overrides=["solver.sleep=false"]).solver.sleep is False
