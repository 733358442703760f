"""The implicit step as a whole: a rigid spin under each method, and effects that cost nothing when off."""

import numpy as np
import taichi as ti
from conftest import box_mesh, make_scene

import fem
from fem.scene import Effects, Initial, Selection, SolverSettings


def spinning(method, omega=4.0, E=2e4, **kw):
    scene = make_scene(box_mesh(3), method, E=E, nu=0.3, density=100.0, **kw)
    scene.initial = [Initial(Selection(None), "spin", (np.array([0.0, 1.0, 0.0]), omega))]
    return scene


def test_rigid_spin_keeps_volume_under_corotation_and_inflates_linear(f64):
    ratios = {}
    for method in ("linear", "corotational"):
        sim = fem.Simulation(spinning(method, omega=6.0, E=1e6))   # stiff: no centrifugal stretch
        worst = 0.0
        for _ in range(60):   # 0.6 s, about half a turn
            sim.step()
            worst = max(worst, abs(sim.stats()["volume_ratio"][0] - 1))
        ratios[method] = worst
    assert ratios["corotational"] < 0.005
    assert ratios["linear"] > 0.1


def launches_per_step(scene, steps=5):
    """{kernel name: launches} over `steps` steps after the first two (Taichi's kernel profiler):
    BDF2's first step is backward Euler's, and the second builds what depends on its own h."""
    fem.init("cpu", "f64")
    ti.init(arch=ti.cpu, default_fp=ti.f64, kernel_profiler=True, log_level=ti.ERROR)
    sim = fem.Simulation(scene)
    sim.step()
    sim.step()
    ti.profiler.clear_kernel_profiler_info()
    for _ in range(steps):
        sim.step()
    ti.sync()
    names = ["extract_rotations", "build_preconditioner", "start_contacts", "gradient_corners",
             "evaluate_first", "evaluate_trial", "start_iterate"]
    # A kernel compiled for two argument sets (the two swapped States) has two record names,
    # name_c<id>_<n>_kernel_<task>_<kind>; its first task (kernel_0) runs once per launch.
    records = [r.name for r in ti.lang.impl.get_runtime().prog.get_kernel_profiler_records()]
    counts = {n: sum(r.startswith(n + "_c") and "_kernel_0_" in r for r in records) for n in names}
    fem.init("cpu", "f64")
    return counts


def test_switched_off_effects_launch_no_work():
    mesh = box_mesh(2)
    linear = launches_per_step(make_scene(mesh, "linear"))
    assert linear["extract_rotations"] == 0            # no corotational body: no rotation ever
    assert linear["build_preconditioner"] == 0         # linear: built once, in the first step
    assert linear["start_contacts"] == 0
    assert linear["evaluate_first"] == 5               # E at the first iterate only: at rest, no iteration
    assert linear["evaluate_trial"] == 0
    assert linear["start_iterate"] == 5
    corot = launches_per_step(make_scene(mesh, "corotational", solver=SolverSettings(step="single")))
    assert corot["extract_rotations"] == 10            # R at x_n, and at BDF2's target x^ (the first iterate)
    assert corot["build_preconditioner"] == 0          # at rest: the first step's blocks still fit
    ground = launches_per_step(make_scene(mesh, "linear", position=(0, 1, 0),
                                          effects=Effects(gravity=(0, -9.81, 0), ground=0.0)))
    assert ground["start_contacts"] == 5
    assert ground["gradient_corners"] == linear["gradient_corners"]   # gravity adds code, not launches


def test_a_newton_step_starts_from_the_rotations_its_last_step_ended_with():
    """R(x_n) of a Newton step is its last step's last trial's, not extracted again: at rest
    (no iteration) BDF2 extracts rotations once a step, at its first iterate, and backward
    Euler, whose first iterate is x_n, not at all."""
    mesh = box_mesh(2)
    assert launches_per_step(make_scene(mesh, "corotational"))["extract_rotations"] == 5
    backward_euler = make_scene(mesh, "corotational", solver=SolverSettings(integrator="backward-euler"))
    assert launches_per_step(backward_euler)["extract_rotations"] == 0
