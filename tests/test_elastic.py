"""The element: stiffness, patch test and rotation extraction, against independent numpy references."""

import numpy as np
import pytest
import scipy.sparse as sp
import taichi as ti
from conftest import box_mesh, make_scene

import fem
from fem.rotation import polar_rotation
from fem.mesh import prepare_mesh


def reference_Ke(X, E, nu):
    """Textbook 12x12 linear tet stiffness W B^T C B (Voigt notation), built independently."""
    Dm = np.column_stack([X[0] - X[3], X[1] - X[3], X[2] - X[3]])
    W = abs(np.linalg.det(Dm)) / 6
    Bm = np.linalg.inv(Dm)
    grads = [Bm[0], Bm[1], Bm[2], -(Bm[0] + Bm[1] + Bm[2])]
    B = np.zeros((6, 12))
    for k, g in enumerate(grads):
        B[0, 3 * k], B[1, 3 * k + 1], B[2, 3 * k + 2] = g
        B[3, 3 * k:3 * k + 3] = [g[1], g[0], 0]
        B[4, 3 * k:3 * k + 3] = [0, g[2], g[1]]
        B[5, 3 * k:3 * k + 3] = [g[2], 0, g[0]]
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    C = np.zeros((6, 6))
    C[:3, :3] = lam
    C[np.arange(3), np.arange(3)] += 2 * mu
    C[3:, 3:] = mu * np.eye(3)
    return W * B.T @ C @ B


def stiffness_from_operator(sim, x=None):
    """K extracted column by column from the matrix-free product (cM = 0, cK = 1) at positions x."""
    n = sim.model.n_vertices
    K = np.zeros((3 * n, 3 * n))
    for j in range(3 * n):
        u = np.zeros((n, 3))
        u.flat[j] = 1.0
        K[:, j] = sim.apply_matrix(u, 0.0, 1.0, x=x).ravel()
    return K


ONE_TET = np.array([[0.1, 0.0, 0.0], [1.0, 0.2, 0.0], [0.0, 1.1, 0.1], [0.2, 0.1, 0.9]])


def test_single_tet_stiffness_is_symmetric_psd_with_six_rigid_modes(f64):
    mesh = prepare_mesh(ONE_TET, np.array([[0, 1, 2, 3]]), "one tet")
    sim = fem.Simulation(make_scene(mesh, "linear", E=1e5, nu=0.3))
    K = stiffness_from_operator(sim)
    eig = np.linalg.eigvalsh(0.5 * (K + K.T))
    assert np.allclose(K, K.T, atol=1e-9 * np.abs(K).max())
    assert eig.min() > -1e-9 * eig.max()
    assert np.sum(np.abs(eig) < 1e-8 * eig.max()) == 6
    np.testing.assert_allclose(K, reference_Ke(mesh.vertices, 1e5, 0.3), atol=1e-9 * np.abs(K).max())


@pytest.mark.parametrize("svd", [False, True])
def test_corotational_stiffness_is_rotated_Ke(f64, svd):
    mesh = prepare_mesh(ONE_TET, np.array([[0, 1, 2, 3]]), "one tet")
    sim = fem.Simulation(make_scene(mesh, "corotational", E=1e5, nu=0.3))
    angle = 0.7
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    sim.settings.rotations = "svd" if svd else "iterative"
    x = mesh.vertices @ R.T + [0.3, -0.2, 0.5]
    np.testing.assert_allclose(sim.rotations(x)[0], R, atol=1e-9)
    Rb = np.kron(np.eye(4), R)
    np.testing.assert_allclose(stiffness_from_operator(sim, x), Rb @ reference_Ke(mesh.vertices, 1e5, 0.3) @ Rb.T,
                               atol=1e-6 * 1e5)
    assert np.abs(sim.forces(x)).max() < 1e-6   # a rigid motion costs no force


def assembled_matrix(sim, cM, cK, x):
    """A = cM M + cK sum_e R Ke R^T assembled with scipy from numpy references (R: exact polar of F)."""
    m = sim.model
    n = m.n_vertices
    rows, cols, vals = [], [], []
    R_all = exact_rotations(m, x) if m.any_corotational else np.tile(np.eye(3), (m.n_tets, 1, 1))
    for e, tet in enumerate(m.tets_np):
        b = m.bodies[m.tet_body_np[e]].material
        Rb = np.kron(np.eye(4), R_all[e])
        Ke = Rb @ reference_Ke(m.rest_positions_np[tet], b.E, b.nu) @ Rb.T
        dofs = (3 * tet[:, None] + np.arange(3)).ravel()
        rows.append(np.repeat(dofs, 12))
        cols.append(np.tile(dofs, 12))
        vals.append(Ke.ravel())
    K = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n, 3 * n))
    M = sp.diags(np.repeat(m.mass_np, 3))
    return cM * M + cK * K


def exact_rotations(model, x):
    """Polar rotations of every tet's F by numpy's SVD (all tets proper here)."""
    X, T = model.rest_positions_np, model.tets_np
    Dm = np.stack([X[T[:, k]] - X[T[:, 3]] for k in range(3)], axis=2)
    Ds = np.stack([x[T[:, k]] - x[T[:, 3]] for k in range(3)], axis=2)
    U, _, Vt = np.linalg.svd(Ds @ np.linalg.inv(Dm))
    return U @ Vt


@pytest.mark.parametrize("method", ["linear", "corotational"])
def test_matrix_free_product_equals_assembled_matrix(f64, method):
    mesh = box_mesh(3)
    sim = fem.Simulation(make_scene(mesh, method, E=5e4, nu=0.4))
    rng = np.random.default_rng(1)
    x = mesh.vertices @ np.linalg.qr(rng.standard_normal((3, 3)))[0].T + 0.05 * rng.standard_normal(mesh.vertices.shape)
    sim.settings.step = "single"          # the Newton matrix without its twist term: exactly R Ke R^T
    cM, cK = 1.1, 2e-3
    A = assembled_matrix(sim, cM, cK, x)
    u = rng.standard_normal((sim.model.n_vertices, 3))
    Au = sim.apply_matrix(u, cM, cK, x=x)
    np.testing.assert_allclose(Au.ravel(), A @ u.ravel(), rtol=0, atol=1e-9 * np.abs(A @ u.ravel()).max())


def test_patch_test_affine_deformation(f64):
    """A uniform strain: zero force on interior vertices, and the forces carry the analytic stress.

    For nodal forces of a uniform stress sigma, sum_i f_i X_i^T = -V sigma (V: body volume).
    """
    mesh = box_mesh(3)
    E, nu = 1e4, 0.3
    sim = fem.Simulation(make_scene(mesh, "linear", E=E, nu=nu))
    G = np.array([[0.01, 0.004, 0.0], [0.002, -0.005, 0.003], [0.0, 0.001, 0.008]])   # displacement gradient
    force = sim.forces(mesh.vertices @ (np.eye(3) + G).T)

    interior = np.all(np.abs(mesh.vertices) < 0.49, axis=1)
    assert interior.sum() == 8
    assert np.abs(force[interior]).max() < 1e-10 * E
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    eps = 0.5 * (G + G.T)
    sigma = 2 * mu * eps + lam * np.trace(eps) * np.eye(3)
    np.testing.assert_allclose(force.T @ mesh.vertices, -1.0 * sigma, atol=1e-9 * E)


@ti.kernel
def _rotations(F: ti.types.ndarray(), R: ti.types.ndarray()):
    for i in range(F.shape[0]):
        M = ti.Matrix.zero(float, 3, 3)
        for a, b in ti.static(ti.ndrange(3, 3)):
            M[a, b] = F[i, a, b]
        Q = polar_rotation(M)
        for a, b in ti.static(ti.ndrange(3, 3)):
            R[i, a, b] = Q[a, b]


def test_rotation_extraction_is_proper_for_degenerate_and_inverted_F(f64):
    rng = np.random.default_rng(0)
    F = np.stack([
        np.zeros((3, 3)),                       # F = 0
        np.diag([1.0, 1.0, 0.0]),               # singular
        np.diag([1.0, 1.0, -1.0]),              # reflected (inverted tet)
        np.diag([-2.0, 0.5, 1.0]) @ np.linalg.qr(rng.standard_normal((3, 3)))[0],
        np.full((3, 3), np.nan),                # non-finite input
        *rng.standard_normal((20, 3, 3)),
    ])
    R = np.zeros_like(F)
    _rotations(F, R)
    for Ri in R:
        np.testing.assert_allclose(Ri @ Ri.T, np.eye(3), atol=1e-9)
        assert np.linalg.det(Ri) == pytest.approx(1.0, abs=1e-9)
    # for a proper F the result is the polar factor: R^T F symmetric positive semi-definite
    for Fi, Ri in zip(F[5:], R[5:]):
        if np.linalg.det(Fi) > 0:
            S = Ri.T @ Fi
            np.testing.assert_allclose(S, S.T, atol=1e-9)
            assert np.linalg.eigvalsh(0.5 * (S + S.T)).min() > -1e-9


def test_iterative_rotations_match_the_svd(f64):
    """The warm-started extraction lands on the SVD's polar rotation, inverted tets included."""
    mesh = box_mesh(3)
    sim = fem.Simulation(make_scene(mesh, "corotational"))
    rng = np.random.default_rng(3)
    Q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))
    x = mesh.vertices @ Q.T + 0.08 * rng.standard_normal(mesh.vertices.shape)
    x[0] = x[1] + (x[1] - x[0]) * 3          # turn some tets inside out
    sim.settings.rotations = "svd"
    exact = sim.rotations(x)
    sim.solver.reset()                       # cold start: identity quaternions
    sim.settings.rotations = "iterative"
    for _ in range(3):                       # three warm-started extractions from the identity
        iterative = sim.rotations(x)
    np.testing.assert_allclose(iterative, exact, atol=1e-6)
    assert np.allclose(np.linalg.det(iterative), 1.0)
