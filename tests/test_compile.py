"""Kernels compile once per process and kind of scene: a second Simulation starts at once."""

import gc

import numpy as np

import fem
from conftest import box_mesh, make_scene
from fem import pool
from fem.scene import Effects


def exercise(sim):
    """Everything a run, a stats file and a colour mode launch."""
    for _ in range(3):
        sim.step()
    sim.stats()
    sim.tet_values()
    sim.apply_impulse([0], (0.1, 0.0, 0.0))


def test_a_second_simulation_of_the_same_kind_compiles_nothing():
    fem.init("cpu", "f32", restart=True)   # nothing compiled yet
    exercise(fem.Simulation(make_scene(box_mesh(2))))
    gc.collect()
    made, compiled = pool.made["parts"], pool.compiled_kernels()
    assert compiled > 10

    # another mesh and material, same effects: the first one's parts, already compiled
    sim = fem.Simulation(make_scene(box_mesh(3), E=3e4, nu=0.45, position=(1, 0, 0)))
    exercise(sim)
    assert (pool.made["parts"], pool.compiled_kernels()) == (made, compiled)
    assert np.isfinite(sim.positions()).all() and sim.model.n_tets == 6 * 27


def test_another_kind_of_scene_compiles_its_own_kernels():
    fem.init("cpu", "f32", restart=True)   # nothing compiled yet
    exercise(fem.Simulation(make_scene(box_mesh(2))))
    gc.collect()
    made, compiled = pool.made["parts"], pool.compiled_kernels()
    alive = fem.Simulation(make_scene(box_mesh(2)))                      # the idle parts are in use now
    with_gravity = fem.Simulation(make_scene(box_mesh(2), effects=Effects(gravity=(0.0, -9.81, 0.0))))
    for sim in (alive, with_gravity):
        exercise(sim)
    assert pool.made["parts"] == made + 1            # `alive` reused the idle parts
    assert pool.compiled_kernels() > compiled        # the gravity kind compiled its own


def test_init_again_with_the_same_settings_keeps_the_kernels_and_a_restart_drops_the_pool():
    import taichi as ti

    fem.init("cpu", "f32")
    exercise(fem.Simulation(make_scene(box_mesh(2))))
    gc.collect()
    made, compiled = pool.made["parts"], pool.compiled_kernels()
    fem.init("cpu", "f32")                               # as every command does: nothing restarts
    exercise(fem.Simulation(make_scene(box_mesh(2))))
    assert (pool.made["parts"], pool.compiled_kernels()) == (made, compiled)

    gc.collect()
    ti.init(arch=ti.cpu, default_fp=ti.f32, log_level=ti.ERROR)   # behind fem's back: idle fields are gone
    sim = fem.Simulation(make_scene(box_mesh(2)))
    exercise(sim)
    assert pool.made["parts"] == made + 1 and np.isfinite(sim.positions()).all()
    fem.init("cpu", "f32", restart=True)                # leave Taichi as fem.init makes it


def test_taichi_starts_with_the_gpu_loops_grid_of_fem_runtime_and_again_when_it_changes(monkeypatch):
    """GPU_GRID_BLOCKS reaches Taichi (its kernels compile with it: a GPU loop's blocks), and
    tools/gpu_tune.py's change of it restarts Taichi at the next init."""
    import taichi as ti

    fem.init("cpu", "f32")
    assert ti.lang.impl.current_cfg().saturating_grid_dim == fem.runtime.GPU_GRID_BLOCKS
    running = ti.lang.impl.get_runtime()
    monkeypatch.setattr(fem.runtime, "GPU_GRID_BLOCKS", 512)
    fem.init("cpu", "f32")
    assert ti.lang.impl.get_runtime() is not running and ti.lang.impl.current_cfg().saturating_grid_dim == 512
    monkeypatch.undo()
    fem.init("cpu", "f32")                               # leave Taichi as fem.init makes it
    assert ti.lang.impl.current_cfg().saturating_grid_dim == fem.runtime.GPU_GRID_BLOCKS


def test_a_functions_source_is_read_once_however_many_kernels_call_it():
    import taichi as ti
    from taichi.lang import kernel_impl

    fem.init("cpu", "f32")

    @ti.func
    def cube(a):
        return a * a * a

    @ti.kernel
    def sum_of_cubes(n: ti.i32) -> ti.i32:
        total = 0
        for i in range(n):
            total += cube(i) + cube(i)        # two call sites, each translated
        return total

    @ti.kernel
    def cube_of(a: ti.i32) -> ti.i32:
        return cube(a)

    before = kernel_impl.getsourcelines.cache_info()
    assert sum_of_cubes(4) == 2 * (0 + 1 + 8 + 27) and cube_of(5) == 125
    after = kernel_impl.getsourcelines.cache_info()
    assert after.misses - before.misses == 3          # the two kernels and `cube`, each once
    assert after.hits - before.hits >= 2              # `cube` at its other two call sites
