"""The benchmark: the direct baseline agrees with the engine, and `bench` writes every file and row.

Timings are never asserted: they are what the benchmark measures.
"""

import json

import numpy as np
import pytest
from conftest import box_mesh, make_scene

import fem
import main
from app import bench
from app.direct import DirectSolver, polar_rotations
from fem.scene import Effects, Initial, Selection, SolverSettings


def twisted_spinning_box(method, effects=None, pinned=None):
    scene = make_scene(box_mesh(3), method, E=1e4, nu=0.3, density=100.0, effects=effects, pinned=pinned,
                       solver=SolverSettings(dt=0.01, tolerance=1e-10, max_iterations=500, rotations="svd"))
    scene.initial = [Initial(Selection(None), "twist_shape", (np.array([1.0, 0, 0]), np.radians(60))),
                     Initial(Selection(None), "spin", (np.array([0.0, 0, 1.0]), 2.0))]
    return scene


@pytest.mark.parametrize("method", ["linear", "corotational"])
def test_direct_step_equals_the_engine_step(f64, method):
    sim = fem.Simulation(twisted_spinning_box(method), step="single")
    solver = DirectSolver(sim)
    sim.step()
    solver.step()
    np.testing.assert_allclose(solver.x, sim.positions(), atol=1e-10)
    np.testing.assert_allclose(solver.v, sim.velocities(), atol=1e-8)


def test_direct_matches_the_engine_with_every_effect(f64):
    """Gravity, Rayleigh damping, pins and the ground over several steps."""
    effects = Effects(gravity=(0.0, -9.81, 0.0), ground=-0.6, alpha=0.1, beta=0.01)
    sim = fem.Simulation(twisted_spinning_box("corotational", effects, pinned=[0, 1]), step="single")
    solver = DirectSolver(sim)
    for _ in range(20):
        sim.step()
        solver.step()
    assert solver.x[:, 1].min() >= -0.6
    assert not solver.v[[0, 1]].any()
    np.testing.assert_allclose(solver.x, sim.positions(), atol=1e-9)


def test_polar_rotations_are_proper_also_for_inverted_tets():
    rng = np.random.default_rng(1)
    F = rng.standard_normal((200, 3, 3))
    R = polar_rotations(F)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    upright = np.linalg.det(F) > 0   # there R^T F is the symmetric positive stretch
    S = np.swapaxes(R, 1, 2) @ F
    np.testing.assert_allclose(S[upright], np.swapaxes(S[upright], 1, 2), atol=1e-12)


def run_bench(tmp_path, *extra):
    args = main.build_parser().parse_args(["bench", "--out", str(tmp_path), "--precision", "f64", *extra])
    return bench.run(args, plan=bench.TEST)


@pytest.fixture(scope="module")
def bench_output(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    assert run_bench(out) == 0
    return out


def test_bench_writes_all_three_files(bench_output):
    assert (bench_output / "accuracy_vs_time.png").read_bytes().startswith(b"\x89PNG")
    md = (bench_output / "results.md").read_text()
    for word in ("linear", "corotational", "PCG", "Jacobi", "direct", "reference", "err 0.2 s", "Corotation costs"):
        assert word in md
    assert json.loads((bench_output / "results.json").read_text())["headline"]


def test_bench_has_every_variant_with_an_error(bench_output):
    results = json.loads((bench_output / "results.json").read_text())
    (scene,) = results["scenes"]
    rows = {(r["method"], r["solver"], r["tolerance"], r["iterations"]): r for r in scene["variants"]}
    for method in ("linear", "corotational"):
        for tol in bench.PCG_TOLERANCES:
            assert (method, "pcg", tol, None) in rows
        for k in bench.JACOBI_ITERATIONS:
            assert (method, "jacobi", None, k) in rows
        assert (method, "direct", None, None) in rows
    for row in rows.values():
        assert set(row["errors"]) == {"0.1", "0.2"}
        assert all(e is not None and e >= 0 for e in row["errors"].values())
        assert row["ms_median"] > 0 and row["bytes_per_tet"] > 0


def test_bench_errors_measure_physics(bench_output):
    """The exact direct solve sits on the reference; linear FEM of a spinning bar is far off."""
    (scene,) = json.loads((bench_output / "results.json").read_text())["scenes"]
    error = {r["label"]: r["errors"]["0.2"] for r in scene["variants"]}
    assert error["corotational direct"] < 1e-7
    assert error["linear direct"] > 1e-3
    assert error["corotational PCG 1e-2"] > error["corotational PCG 1e-6"]


def test_bench_refuses_a_non_empty_folder(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(fem.FemError, match="--overwrite"):
        run_bench(tmp_path)
