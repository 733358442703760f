"""The wrong corotational variant f = -R Ke R^T (x - X), kept as a teaching switch.

Checked against an independent assembly (app.bench.direct's textbook 12x12 element blocks and
numpy SVD rotations), and against the right variant under a pure rotation."""

import subprocess
import sys

import numpy as np
import pytest

import fem
from app.bench.direct import element_stiffness, polar_rotations, shape_gradients
from conftest import ROOT, box_mesh, make_scene

E, NU = 1e4, 0.3


def rotation_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def naive_forces(X, T, x):
    """-R Ke R^T (x - X) per tet, summed into the vertices: the coursework listing's formula."""
    g, W = shape_gradients(X, T)
    mu, lam = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))
    Ke = element_stiffness(g, W, np.full(len(T), mu), np.full(len(T), lam))
    Dm = np.stack([X[T[:, k]] - X[T[:, 3]] for k in range(3)], axis=2)
    Ds = np.stack([x[T[:, k]] - x[T[:, 3]] for k in range(3)], axis=2)
    R = polar_rotations(Ds @ np.linalg.inv(Dm))
    u = np.einsum("eji,eaj->eai", R, x[T] - X[T])                  # R^T (x - X) per corner
    f = -np.einsum("eij,eajbk,ebk->eai", R, Ke, u)                  # R Ke (R^T u)
    out = np.zeros_like(X)
    np.add.at(out, T.ravel(), f.reshape(-1, 3))
    return out


@pytest.fixture(scope="module")
def sims(f64):
    mesh = box_mesh(2)
    return mesh, {m: fem.Simulation(make_scene(mesh, m, E=E, nu=NU))
                  for m in ("corotational", "corotational-naive")}


def test_naive_forces_are_R_Ke_R_transpose_times_the_displacement(sims):
    mesh, sim = sims
    x = mesh.vertices @ rotation_z(0.9).T + 0.02 * np.random.default_rng(1).standard_normal(mesh.vertices.shape)
    expected = naive_forces(mesh.vertices, mesh.tets, x)
    assert np.allclose(sim["corotational-naive"].forces(x), expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_only_the_naive_variant_pushes_on_a_pure_rotation(sims):
    mesh, sim = sims
    x = mesh.vertices @ rotation_z(0.9).T
    scale = E * 1.0                               # N: stiffness times the cube's 1 m^2 cross-section
    assert np.abs(sim["corotational"].forces(x)).max() < 1e-9 * scale
    assert np.abs(sim["corotational-naive"].forces(x)).max() > 0.05 * scale


def test_naive_takes_the_one_solve_step_from_the_command_line(tmp_path):
    result = subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", "cube86", "--naive",
                             "--steps", "3", "--stats", str(tmp_path / "s.jsonl")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    rows = (tmp_path / "s.jsonl").read_text().splitlines()
    assert len(rows) == 3 and all('"newton_iters": 1' in row for row in rows)
