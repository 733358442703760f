"""The implicit step: conservation, dissipation, convergence, and effects that cost nothing when off."""

from dataclasses import replace

import numpy as np
import pytest
import taichi as ti
from conftest import box_mesh, make_scene

import fem
from fem.scene import Effects, Initial, Selection, SolverSettings


def momentum(sim):
    return (sim.model.mass_np[:, None] * sim.velocities()).sum(axis=0)


def angular_momentum(sim):
    x, v = sim.positions(), sim.velocities()
    return (sim.model.mass_np[:, None] * np.cross(x, v)).sum(axis=0)


def spinning(method, omega=4.0, E=2e4, **kw):
    scene = make_scene(box_mesh(3), method, E=E, nu=0.3, density=100.0, **kw)
    scene.initial = [Initial(Selection(None), "spin", (np.array([0.0, 1.0, 0.0]), omega))]
    return scene


@pytest.mark.parametrize("method", ["linear", "corotational"])
def test_momentum_is_conserved_without_effects(f64, method):
    scene = spinning(method)
    scene.initial.append(Initial(Selection(0, vertices=np.array([0, 5])), "velocity", (np.array([3.0, -1.0, 2.0]),)))
    sim = fem.Simulation(scene)
    p0, L0 = momentum(sim), angular_momentum(sim)
    for _ in range(30):
        sim.step()
    scale = np.abs(sim.model.mass_np).sum() * 4.0
    np.testing.assert_allclose(momentum(sim), p0, atol=1e-9 * scale)
    if method == "corotational":
        # backward Euler does not conserve angular momentum: L' - L = -dt^2 sum v' x f(x'); it
        # only loses some (here ~4 % in 30 steps; the one-solve step's linearisation ~1 %)
        L = angular_momentum(sim)
        assert np.linalg.norm(L) <= np.linalg.norm(L0)
        np.testing.assert_allclose(L, L0, atol=0.05 * np.linalg.norm(L0))


@pytest.mark.parametrize("method", ["linear", "corotational"])
def test_total_energy_never_rises_with_damping(f64, method):
    scene = make_scene(box_mesh(3), method, E=1e4, nu=0.3, density=100.0,
                       effects=Effects(alpha=0.1, beta=0.01))
    scene.initial = [Initial(Selection(None), "twist_shape", (np.array([1.0, 0, 0]), np.radians(60))),
                     Initial(Selection(None), "spin", (np.array([0.0, 0, 1.0]), 2.0))]
    sim = fem.Simulation(scene)
    energies = [sim.stats()["total_energy"]]
    for _ in range(60):
        sim.step()
        energies.append(sim.stats()["total_energy"])
    energies = np.array(energies)
    assert energies[-1] < 0.5 * energies[0]
    assert np.all(np.diff(energies) <= 1e-6 * energies[0])


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


def test_pcg_reaches_tolerance_and_reports_iterations(f64):
    """A single step solves H v' = M v + dt f(x) to the tolerance it reports (no gravity, no damping)."""
    scene = spinning("corotational", solver=SolverSettings(dt=0.02, tolerance=1e-8, max_iterations=400,
                                                           step="single"))
    scene.initial.append(Initial(Selection(None), "stretch", (np.array([1.0, 0, 0]), 1.3)))
    sim = fem.Simulation(scene)
    x, v = sim.positions(), sim.velocities()
    momentum, impulse = sim.model.mass_np[:, None] * v, 0.02 * sim.forces(x)
    info = sim.step()
    residual = momentum + impulse - sim.apply_matrix(sim.velocities(), x=x)
    true_residual = np.linalg.norm(residual) / np.sqrt(np.sum(momentum ** 2) + np.sum(impulse ** 2))
    assert info["converged"] and 0 < info["solver_iters"] < 400 and info["newton_iters"] == 1
    assert info["residual"] <= 1e-8
    assert true_residual == pytest.approx(info["residual"], rel=1e-3, abs=1e-12)


def test_the_first_guess_extrapolates_the_last_steps_change(f64):
    """Each solve starts from v_n + (dt / dt_prev)(v_n - v_(n-1)). Falling freely, a body's velocity changes by
    g dt every step: from the second step on that guess is the answer and PCG has nothing left
    to do, where a start from v_n needs iterations. A new state (set_state) starts from v_n
    alone; a rejected step leaves no NaN in the guess."""
    g, dt = np.array([0.0, -9.81, 0.0]), 0.02
    runs = {}
    for forget in (False, True):
        scene = spinning("corotational", omega=0.0, effects=Effects(gravity=tuple(g)),
                         solver=SolverSettings(dt=dt, tolerance=1e-6, step="single"))
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
    assert np.isfinite(sim.solver.change.to_numpy()).all()


def test_iteration_cap_is_reported_not_hidden(f64):
    scene = spinning("corotational", solver=SolverSettings(dt=0.02, tolerance=1e-12, max_iterations=3,
                                                           step="single"))
    scene.initial.append(Initial(Selection(None), "stretch", (np.array([1.0, 0, 0]), 1.3)))
    info = fem.Simulation(scene).step()
    assert info["solver_iters"] == 3 and not info["converged"] and info["residual"] > 1e-12


def test_jacobi_converges_to_the_pcg_solution(f64):
    solutions = {}
    for solver in ("pcg", "jacobi"):
        scene = spinning("corotational", solver=SolverSettings(dt=0.01, method=solver, tolerance=1e-9,
                                                               max_iterations=5000, newton_tolerance=1e-9))
        scene.initial.append(Initial(Selection(None), "stretch", (np.array([1.0, 0, 0]), 1.3)))
        sim = fem.Simulation(scene)
        info = sim.step()
        assert info["converged"], info
        solutions[solver] = sim.velocities()
    np.testing.assert_allclose(solutions["jacobi"], solutions["pcg"], atol=1e-6)


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


def launches_per_step(scene, steps=5):
    """{kernel name: launches} over `steps` steps after the first (Taichi's kernel profiler)."""
    fem.init("cpu", "f64")
    ti.init(arch=ti.cpu, default_fp=ti.f64, kernel_profiler=True, log_level=ti.ERROR)
    sim = fem.Simulation(scene)
    sim.step()
    ti.profiler.clear_kernel_profiler_info()
    for _ in range(steps):
        sim.step()
    ti.sync()
    names = ["extract_rotations", "build_preconditioner", "ground_contact", "gradient_corners",
             "energy_tets", "start_iterate"]
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
    assert linear["ground_contact"] == 0
    assert linear["energy_tets"] == 0                  # one Newton iteration is exact: no line search
    assert linear["start_iterate"] == 5
    corot = launches_per_step(make_scene(mesh, "corotational", solver=SolverSettings(step="single")))
    assert corot["extract_rotations"] == 5
    assert corot["build_preconditioner"] == 0          # at rest: the first step's blocks still fit
    ground = launches_per_step(make_scene(mesh, "linear", position=(0, 1, 0),
                                          effects=Effects(gravity=(0, -9.81, 0), ground=0.0)))
    assert ground["ground_contact"] == 5
    assert ground["gradient_corners"] == linear["gradient_corners"]   # gravity adds code, not launches


def test_block_jacobi_is_rebuilt_only_once_the_tets_turned_stale_turn(f64, monkeypatch):
    """One-solve step: no tet is ever more than STALE_TURN from the rotation its block was built
    with, a body spinning at 0.04 rad a step rebuilds about every sixth step, and PCG needs as
    many iterations as with blocks rebuilt every step."""
    iterations = {}
    for stale_turn in (0.0, fem.solver.STALE_TURN):
        monkeypatch.setattr(fem.solver, "STALE_TURN", stale_turn)
        sim = fem.Simulation(spinning("corotational", solver=SolverSettings(step="single", dt=0.01)))
        solver, m = sim.solver, sim.model.n_tets
        built, build = [], solver.build_preconditioner

        def recording(cM, cK):
            build(cM, cK)
            built.append(solver.quaternions.to_numpy()[:m])

        monkeypatch.setattr(solver, "build_preconditioner", recording)
        turned, total = [], 0
        for _ in range(60):
            total += sim.step()["solver_iters"]
            q = solver.quaternions.to_numpy()[:m]            # R(x_n): what the step's solve used
            turned.append(2 * np.arccos(np.minimum(np.abs((q * built[-1]).sum(axis=1)), 1.0)).max())
        iterations[stale_turn] = total
    assert max(turned) <= fem.solver.STALE_TURN + 1e-9
    assert max(turned) > 0.5 * fem.solver.STALE_TURN          # the blocks did go stale
    assert 60 / 8 <= len(built) <= 60 / 4
    assert iterations[fem.solver.STALE_TURN] <= 1.05 * iterations[0.0]


def test_block_jacobi_is_rebuilt_after_an_impulse_a_new_state_and_a_live_edit(f64, monkeypatch):
    sim = fem.Simulation(spinning("corotational", solver=SolverSettings(step="single", dt=0.01)))
    builds = []
    build = sim.solver.build_preconditioner
    monkeypatch.setattr(sim.solver, "build_preconditioner", lambda cM, cK: builds.append(1) or build(cM, cK))
    sim.step()
    edits = [lambda: None, lambda: sim.apply_impulse([0], (0.0, 1.0, 0.0)),
             lambda: sim.set_state(sim.positions(), sim.velocities()), lambda: sim.set_material(0, 3e4, 0.3),
             lambda: sim.set_method("corotational"), lambda: sim.rotations()]
    counts = []
    for edit in edits:
        edit()
        before = len(builds)
        sim.step()
        counts.append(len(builds) - before)
    assert counts == [0, 1, 1, 1, 1, 1]
