"""Per-tet elasticity: one formula serves the force, the matrix-free product and the stats.

Symbols (Sifakis & Barbic 2012):
    Ds  columns x0-x3, x1-x3, x2-x3 of a tet's current corners (3x3)
    Bm  inverse of the same matrix at rest (3x3), so F = Ds Bm
    W   rest volume (m^3);  mu, lam  Lame parameters (Pa)
    R   polar rotation of F (identity for linear tets)
The solver uses these through Bm R^T (see fem/solver.py), the stats through R.
"""

import taichi as ti


@ti.func
def edge_matrix(a, b, c, d):
    """Columns a-d, b-d, c-d: the Ds of a tet with corners a, b, c, d."""
    return ti.Matrix.cols([a - d, b - d, c - d])


@ti.func
def linear_stress(eps, mu, lam):
    """Small-strain stress sigma = 2 mu eps + lam tr(eps) I (Pa)."""
    return 2.0 * mu * eps + lam * eps.trace() * ti.Matrix.identity(float, 3)


@ti.func
def corner_forces(P, Bm, W):
    """Forces on the four corners of a tet with first Piola stress P (N).

    H = -W P Bm^T holds the forces on corners 0..2 in its columns; corner 3
    gets minus their sum, so the tet exerts no net force.
    """
    H = -W * P @ Bm.transpose()
    f0 = ti.Vector([H[0, 0], H[1, 0], H[2, 0]])
    f1 = ti.Vector([H[0, 1], H[1, 1], H[2, 1]])
    f2 = ti.Vector([H[0, 2], H[1, 2], H[2, 2]])
    return f0, f1, f2, -(f0 + f1 + f2)


@ti.func
def is_finite(s):
    """True unless s is NaN or +-inf (or beyond 1e30, which no sane state reaches)."""
    return ti.abs(s) < 1e30


@ti.func
def polar_rotation(F):
    """Proper rotation nearest to F (det R = +1), also for inverted or degenerate F.

    F = U S V^T by SVD, R = U V^T. Taichi's SVD returns proper rotations U, V and
    puts a reflection into the smallest singular value, which is the
    inversion-safe choice of Irving et al. 2004; the determinant check keeps
    that promise if a future SVD does not. A non-finite F gives the identity.
    """
    R = ti.Matrix.identity(float, 3)
    if is_finite(F.sum()):
        U, S, V = ti.svd(F)
        if (U @ V.transpose()).determinant() < 0:
            k = 0
            for j in ti.static(range(1, 3)):
                if ti.abs(S[j, j]) < ti.abs(S[k, k]):
                    k = j
            for i in ti.static(range(3)):
                U[i, k] = -U[i, k]
        R = U @ V.transpose()
    return R


@ti.func
def quaternion_matrix(q):
    """Rotation matrix of a unit quaternion q = (x, y, z, w)."""
    x, y, z, w = q[0], q[1], q[2], q[3]
    return ti.Matrix([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


@ti.func
def refine_rotation(F, q, max_iterations: ti.template()):
    """Turn the unit quaternion q into the polar rotation of F by Newton steps on tr(R^T F).

    The axis of Mueller et al. 2016, omega = sum_i r_i x f_i (r_i, f_i: columns of
    R(q) and F), scaled by the inverse of the Hessian tr(S) I - S with S = sym(F R^T)
    instead of by 1 / tr(S): quadratic instead of linear convergence, so a warm
    start from the previous step needs one or two steps, far cheaper than an SVD.
    Where the Hessian is not positive definite (far from the answer) it takes
    Mueller's step. The result is a proper rotation by construction.
    """
    for _ in range(max_iterations):
        R = quaternion_matrix(q)
        omega = ti.Vector.zero(float, 3)
        for i in ti.static(range(3)):
            omega += ti.Vector([R[0, i], R[1, i], R[2, i]]).cross(ti.Vector([F[0, i], F[1, i], F[2, i]]))
        B = F @ R.transpose()
        S = 0.5 * (B + B.transpose())
        H = S.trace() * ti.Matrix.identity(float, 3) - S
        minor = H[0, 0] * H[1, 1] - H[0, 1] * H[1, 0]
        step = omega / (ti.abs(S.trace()) + 1e-9)
        if H[0, 0] > 0 and minor > 0 and H.determinant() > 0:
            step = H.inverse() @ omega
        w = step.norm()
        if w > 0:
            axis = step / w
            s, c = ti.sin(0.5 * w), ti.cos(0.5 * w)
            # q <- (rotation by w about axis) * q, Hamilton product in (x, y, z, w) layout
            p = ti.Vector([s * axis[0], s * axis[1], s * axis[2], c])
            q = ti.Vector([
                p[3] * q[0] + p[0] * q[3] + p[1] * q[2] - p[2] * q[1],
                p[3] * q[1] - p[0] * q[2] + p[1] * q[3] + p[2] * q[0],
                p[3] * q[2] + p[0] * q[1] - p[1] * q[0] + p[2] * q[3],
                p[3] * q[3] - p[0] * q[0] - p[1] * q[1] - p[2] * q[2],
            ]).normalized()
        if w < 1e-5:   # converging quadratically: the error left is ~w^2
            break
    return q


@ti.func
def strain_energy_density(F, R, mu, lam):
    """psi = mu eps:eps + lam/2 tr(eps)^2 with eps = sym(R^T F) - I (J/m^3)."""
    Fr = R.transpose() @ F
    eps = 0.5 * (Fr + Fr.transpose()) - ti.Matrix.identity(float, 3)
    return mu * (eps * eps).sum() + 0.5 * lam * eps.trace() ** 2


@ti.func
def stiffness_block(h, W, mu, lam):
    """Diagonal 3x3 block of R Ke R^T for a corner whose rotated shape gradient is h = R g.

    Ke's block is W (lam g g^T + mu (g.g I + g g^T)); rotating it only turns g into R g.
    """
    hh = h.outer_product(h)
    return W * (lam * hh + mu * (h.dot(h) * ti.Matrix.identity(float, 3) + hh))
