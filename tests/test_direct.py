"""The direct baseline (app/bench/direct.py): every backend steps as the engine's one-solve step does, and
refactorising on an analysis made once gives the factor a fresh analysis would."""

import tomllib

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from conftest import ROOT, box_mesh, make_scene

import fem
from app.bench import direct
from app.bench.direct import BACKENDS, DirectSolver, polar_rotations
from fem.scene import Effects, Initial, Selection, SolverSettings

HOW_TO_INSTALL = {"pardiso": 'pypardiso is not installed (the optional extra: pip install ".[fast-direct]")',
                  "cholmod": "scikit-sparse is not installed (optional)"}


@pytest.fixture(params=list(BACKENDS))
def backend(request):
    """Each backend's name; skips those not installed here."""
    if not direct.INSTALLED[request.param]:
        pytest.skip(HOW_TO_INSTALL[request.param])
    return request.param


def twisted_spinning_box(method, effects=None, pinned=None):
    scene = make_scene(box_mesh(3), method, E=1e4, nu=0.3, density=100.0, effects=effects, pinned=pinned,
                       solver=SolverSettings(dt=0.01, tolerance=1e-10, max_iterations=500, rotations="svd",
                                             integrator="backward-euler"))   # the baseline's integrator
    scene.initial = [Initial(Selection(None), "twist_shape", (np.array([1.0, 0, 0]), np.radians(60))),
                     Initial(Selection(None), "spin", (np.array([0.0, 0, 1.0]), 2.0))]
    return scene


@pytest.mark.parametrize("method", ["linear", "corotational", "corotational-naive"])
def test_direct_step_equals_the_engine_step(f64, method, backend):
    sim = fem.Simulation(twisted_spinning_box(method), step="single")
    solver = DirectSolver(sim, backend)
    sim.step()
    solver.step()
    np.testing.assert_allclose(solver.x, sim.positions(), atol=1e-10)
    np.testing.assert_allclose(solver.v, sim.velocities(), atol=1e-8)


def test_direct_matches_the_engine_with_every_effect(f64, backend):
    """Gravity, Rayleigh damping, pins and the ground over several steps: the contacts come and go,
    so the fixed dofs change while the analysed pattern stays."""
    effects = Effects(gravity=(0.0, -9.81, 0.0), ground=-0.6, alpha=0.1, beta=0.01)
    sim = fem.Simulation(twisted_spinning_box("corotational", effects, pinned=[0, 1]), step="single",
                         tolerance=1e-12)
    solver = DirectSolver(sim, backend)
    contacts = set()
    for _ in range(20):
        sim.step()
        solver.step()
        contacts.add(int((solver.x[:, 1] < -0.6).sum()))
    assert len(contacts) > 2                     # none, then contacts made and let go
    assert solver.x[2:, 1].min() >= -0.6 - 1e-2  # the free vertices: the penalty lets the plane give a little
    assert not solver.v[[0, 1]].any()
    np.testing.assert_allclose(solver.x, sim.positions(), atol=1e-9)


def test_a_factor_on_the_first_analysis_equals_a_fresh_one(f64, backend):
    """Thirty steps on, the spin has turned the element matrices by 0.6 rad; refactorising on the
    analysis made at the start solves A x = b as an analysis of today's A does, and as scipy does."""
    sim = fem.Simulation(twisted_spinning_box("corotational"), step="single")
    solver = DirectSolver(sim, backend)
    start = solver.A.copy()
    for _ in range(30):
        solver.step()
    A = solver.constrained(solver.fixed)
    stiffness = start - sp.diags(start.diagonal())          # off the diagonal, A is cK K(R) alone
    assert abs(A - start).max() > 0.3 * abs(stiffness).max()
    solver.backend.factorise(A)
    fresh = BACKENDS[backend](A)
    fresh.factorise(A)
    b = np.random.default_rng(0).standard_normal(A.shape[0])
    exact = spla.spsolve(A.tocsc(), b)
    np.testing.assert_allclose(solver.backend.solve(b), exact, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fresh.solve(b), exact, rtol=1e-9, atol=1e-12)


def test_the_factor_is_counted_in_the_memory(f64, backend):
    sim = fem.Simulation(twisted_spinning_box("corotational"), step="single")
    solver = DirectSolver(sim, backend)
    solver.step()
    A = solver.A
    assert solver.memory_bytes > A.data.nbytes + A.indices.nbytes + A.indptr.nbytes + A.nnz * 8


def test_the_default_backend_is_the_fastest_installed(f64, monkeypatch):
    for installed, fastest in (({"pardiso", "cholmod"}, "pardiso"), ({"cholmod"}, "cholmod"), (set(), "superlu")):
        monkeypatch.setattr(direct, "INSTALLED", {name: name in installed or name == "superlu" for name in BACKENDS})
        assert direct.fastest_available() == fastest
    monkeypatch.undo()
    sim = fem.Simulation(twisted_spinning_box("linear"), step="single")
    assert DirectSolver(sim).backend_name == direct.fastest_available()


def test_the_fast_solver_is_an_optional_extra_only():
    """The app runs without pypardiso (CI installs requirements.txt only); pip can add it."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert any(d.startswith("pypardiso") for d in project["project"]["optional-dependencies"]["fast-direct"])
    assert "pypardiso" not in (ROOT / "requirements.txt").read_text()


def test_polar_rotations_are_proper_also_for_inverted_tets():
    rng = np.random.default_rng(1)
    F = rng.standard_normal((200, 3, 3))
    R = polar_rotations(F)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    upright = np.linalg.det(F) > 0   # there R^T F is the symmetric positive stretch
    S = np.swapaxes(R, 1, 2) @ F
    np.testing.assert_allclose(S[upright], np.swapaxes(S[upright], 1, 2), atol=1e-12)
