"""The rotation of a deformation gradient F: the R that maximises tr(R^T F) over rotations.

For det F > 0 that is the polar rotation (F = R S, S symmetric positive definite);
for an inverted tet (det F < 0) it is the inversion-safe rotation of Irving et
al. 2004 (the SVD's U V^T with the column of the smallest singular value flipped).

`rotation_of(F, q)` is the routine the solver follows every step (split over two
kernels there, `extract_rotations` and `svd_rotations`, so the SVD compiles only
when needed): Newton steps on
tr(R^T F) (Mueller et al. 2016 with the exact Hessian) from the previous step's
rotation q (the solver turns it on by the last step's turn first); from a warm
start one or two of them in f32, two or three in f64, about a sixth of the cost
of an SVD (tools/rotation_cost.py). The iteration is trusted
only when it certifies its own answer; otherwise R comes from
`polar_rotation(F)`, which needs no start: the SVD, polished by the same Newton
steps. Either way the quaternion of the returned R is the next warm start.

Quaternions are (x, y, z, w), w the scalar part.
"""

import taichi as ti

from fem.elastic import is_finite

# Newton steps per start. A start that needs more is about a radian off or more
# (tools/rotation_cost.py): the SVD costs less than further steps would.
NEWTON_ITERATIONS = 4


def single_precision():
    """True when the fields are float32 (read on the Python side when a kernel compiles)."""
    return ti.lang.impl.get_runtime().default_fp == ti.f32


def real_type(dtype):
    """Taichi's float type for `dtype` (Python's float: the fields' own, f32 or f64)."""
    return ti.lang.impl.get_runtime().default_fp if dtype is float else dtype


def angle_tolerance(dtype=None):
    """Accepted error of a Newton-extracted R (rad), a little above the rounding of `dtype`
    (None: the fields' float type, read when a kernel compiles, after Taichi's is fixed)."""
    single = real_type(float if dtype is None else dtype) == ti.f32
    return 1e-5 if single else 1e-12


@ti.func
def rotation_of(F, q):
    """(R, q_new): the rotation of F (det R = +1) and its quaternion, from the warm start q.

    Newton steps from q (`newton_rotation`); where they cannot certify their answer
    (a start far off, or R ill-defined), `polar_rotation(F)`. q_new is always
    the quaternion of the R returned, so the next warm start is right.
    """
    q, converged = newton_rotation(F, q)
    R = quaternion_matrix(q)
    if not converged:
        R = polar_rotation(F)
        q = quaternion_of(R)
    return R, q


@ti.func
def polar_rotation(F):
    """The rotation of F without a start (det R = +1), also for inverted, flat or non-finite F.

    The SVD's rotation (`svd_rotation`) is global but only as accurate as its fixed
    number of Jacobi sweeps (measured up to 2e-2 rad in f32 and 3e-6 in f64 for a
    50:1 stretch), so Newton steps polish it; where they cannot certify an answer
    (F flat in two directions, or two singular values of an inverted F nearly
    equal: R barely defined), the SVD's rotation as it is. F is scaled to entries
    of size 1 first: R does not depend on its size, and the SVD squares it (in
    f32, F^T F overflows beyond 1e19).

    With float32 fields the whole routine runs in float64: where two singular values are
    below about 1e-4 of the largest, float32's SVD and Newton steps both lose R (measured:
    tens of degrees off on 1 in 50 random F of that kind, tests/test_rotation.py), while
    the float32 rounding of F itself moves R by well under a degree. It is the fallback
    of a few tets, so its cost does not show.
    """
    R = ti.Matrix.identity(float, 3)
    if ti.static(single_precision()):
        R = ti.cast(polar_rotation_in(ti.cast(F, ti.f64), ti.f64), float)
    else:
        R = polar_rotation_in(F, float)
    return R


@ti.func
def polar_rotation_in(F, dtype: ti.template()):
    """polar_rotation(F) with F and every step of the arithmetic in `dtype`."""
    size = ti.abs(F).max()
    G = F
    if size > 0:
        G = F / size
    R = svd_rotation(G, dtype)
    q, converged = newton_rotation(G, quaternion_of(R, dtype), NEWTON_ITERATIONS, dtype)
    if converged:
        R = quaternion_matrix(q)
    return R


@ti.func
def newton_rotation(F, q, max_iterations: ti.template() = NEWTON_ITERATIONS, dtype: ti.template() = float):
    """(q, converged): the quaternion q moved towards the rotation of F by Newton steps.

    With R = R(q), the ascent axis omega = sum_i r_i x f_i (columns of R and F)
    vanishes where R^T F is symmetric, and H = tr(S) I - S with S = sym(F R^T) is
    the Hessian of -tr(R^T F) over rotations; a step rotates R by H^-1 omega.
    At a stationary point R^T F is symmetric with eigenvalues +-s_i (the singular
    values of F) and H's eigenvalues are their pairwise sums, so H is positive
    definite at the maximum only (the answer) and only where that is unique
    (s2 + s3 > 0, or s2 > s3 for an inverted F). A positive definite H near a
    stationary point therefore certifies the right one.

    Converged: H positive definite and the error left after the last step d below
    `angle_tolerance()`. That error is about |F| / lambda_min(H) |d|^3: Newton's
    error is H^-1 times the second-order remainder of the gradient, which here
    is proportional to the gradient itself (the skew part of F R^T), so the
    convergence is cubic, not only quadratic (one turn by theta about the right
    axis leaves theta^3 / 3). The test bounds |F| / lambda_min(H) by
    tr(H)^3 / (8 det H); measured over random F (stretches to 1000:1, inverted
    F, starts up to 1.5 rad off), the true error stays below 0.1 of the estimate.
    Not converged: H not positive definite at some iterate (a start more than
    about 90 deg off, where a Newton step heads anywhere), values not finite,
    or max_iterations steps used up. dtype: the float type of F, q and the arithmetic.
    """
    converged = False
    for _ in range(max_iterations):
        R = quaternion_matrix(q)
        omega = ti.Vector.zero(dtype, 3)
        for i in ti.static(range(3)):
            omega += ti.Vector([R[0, i], R[1, i], R[2, i]]).cross(ti.Vector([F[0, i], F[1, i], F[2, i]]))
        B = F @ R.transpose()
        S = 0.5 * (B + B.transpose())
        H = S.trace() * ti.Matrix.identity(dtype, 3) - S
        A = symmetric_adjugate(H)
        det_H = H[0, 0] * A[0, 0] + H[0, 1] * A[0, 1] + H[0, 2] * A[0, 2]
        if not (H[0, 0] > 0 and A[2, 2] > 0 and det_H > 0):   # leading minors > 0: H positive definite
            break
        d = (A @ omega) / det_H
        # q <- p q with p = (d/2, 1) / |.|: a turn by 2 atan(|d|/2) = |d| + O(|d|^3) about d
        q = quaternion_product(ti.Vector([0.5 * d[0], 0.5 * d[1], 0.5 * d[2], 1.0]), q).normalized()
        d2 = d.norm_sqr()
        if H.trace() ** 3 / (8.0 * det_H) * d2 * ti.sqrt(d2) < ti.static(angle_tolerance(dtype)):
            converged = True
            break
    return q, converged


@ti.func
def symmetric_adjugate(H):
    """adj(H) = det(H) H^-1 of a symmetric 3x3 H (symmetric too: six cofactors)."""
    a, b, c, d, e, f = H[0, 0], H[0, 1], H[0, 2], H[1, 1], H[1, 2], H[2, 2]
    A01, A02, A12 = c * e - b * f, b * e - c * d, b * c - a * e
    return ti.Matrix([[d * f - e * e, A01, A02], [A01, a * f - c * c, A12], [A02, A12, a * d - b * b]])


@ti.func
def svd_rotation(F, dtype: ti.template() = float):
    """U V^T from the SVD F = U S V^T, det = +1 (Irving et al. 2004); the identity for non-finite F.
    dtype: the float type of F and of the SVD's arithmetic.

    Taichi's SVD returns proper rotations U, V and puts a reflection into the
    smallest singular value, which is the inversion-safe choice; the determinant
    check keeps that promise if a future SVD does not.
    """
    R = ti.Matrix.identity(dtype, 3)
    if is_finite(F.sum()):
        U, S, V = ti.svd(F, ti.f64) if ti.static(dtype == ti.f64) else ti.svd(F)
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
def quaternion_product(p, q):
    """p q: the rotation q followed by p (quaternions (x, y, z, w))."""
    return ti.Vector([
        p[3] * q[0] + p[0] * q[3] + p[1] * q[2] - p[2] * q[1],
        p[3] * q[1] - p[0] * q[2] + p[1] * q[3] + p[2] * q[0],
        p[3] * q[2] + p[0] * q[1] - p[1] * q[0] + p[2] * q[3],
        p[3] * q[3] - p[0] * q[0] - p[1] * q[1] - p[2] * q[2],
    ])


@ti.func
def conjugate(q):
    """q^-1 of a unit quaternion q: the opposite turn."""
    return ti.Vector([-q[0], -q[1], -q[2], q[3]])


@ti.func
def quaternion_of(R, dtype: ti.template() = float):
    """Unit quaternion (x, y, z, w) of a rotation matrix R (Shepperd 1978).

    Each component's square is a sum of diagonal entries; the largest one is
    taken from its square root, so the divisions that give the other three stay
    well away from zero. dtype: the float type of R.
    """
    t = R.trace()
    q = ti.Vector.zero(dtype, 4)
    if t >= R[0, 0] and t >= R[1, 1] and t >= R[2, 2]:           # w largest
        r = ti.sqrt(1.0 + t)
        s = 0.5 / r
        q = ti.Vector([(R[2, 1] - R[1, 2]) * s, (R[0, 2] - R[2, 0]) * s, (R[1, 0] - R[0, 1]) * s, 0.5 * r])
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:                 # x largest
        r = ti.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        s = 0.5 / r
        q = ti.Vector([0.5 * r, (R[0, 1] + R[1, 0]) * s, (R[0, 2] + R[2, 0]) * s, (R[2, 1] - R[1, 2]) * s])
    elif R[1, 1] >= R[2, 2]:                                        # y largest
        r = ti.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        s = 0.5 / r
        q = ti.Vector([(R[0, 1] + R[1, 0]) * s, 0.5 * r, (R[1, 2] + R[2, 1]) * s, (R[0, 2] - R[2, 0]) * s])
    else:                                                           # z largest
        r = ti.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        s = 0.5 / r
        q = ti.Vector([(R[0, 2] + R[2, 0]) * s, (R[1, 2] + R[2, 1]) * s, 0.5 * r, (R[1, 0] - R[0, 1]) * s])
    return q.normalized()
