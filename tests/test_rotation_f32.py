"""Rotations in float32 stay right where F is nearly degenerate (fem/rotation.py: polar_rotation).

Taichi's float32 SVD and Newton steps lose the rotation where two singular values are far
below the largest (measured before the fix: 17 to 83 degrees off on tets with condition
numbers above 1e4). The reference is numpy's float64 SVD of the same float32 F, with the
inversion-safe flip of Irving et al. 2004 for inverted F.
"""

import numpy as np
import taichi as ti

import fem
from fem.rotation import polar_rotation, rotation_of

COUNT = 10_000


def random_rotations(rng, n):
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1)[:, None]
    x, y, z, w = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(n, 3, 3)


def near_degenerate_gradients(seed=1):
    """(COUNT, 3, 3) float32 F = U S V^T: singular values log-uniform in [1e-6, 1] (condition
    numbers up to 1e6), a tenth of them inverted (the smallest singular value negative).

    An inverted F's rotation is only defined up to (rounding of F) / (s2 - |s3|): the
    inverted ones keep s2 - |s3| >= 1e-3 s1, where that is a small fraction of a degree."""
    rng = np.random.default_rng(seed)
    s = np.sort(10 ** rng.uniform(-6, 0, (COUNT, 3)), axis=1)[:, ::-1]
    inverted = (rng.random(COUNT) < 0.1) & (s[:, 1] - s[:, 2] >= 1e-3 * s[:, 0])
    s[inverted, 2] *= -1
    U, V = random_rotations(rng, COUNT), random_rotations(rng, COUNT)
    return np.einsum("nij,nj,nkj->nik", U, s, V).astype(np.float32)


def reference_rotations(F):
    """Inversion-safe rotation of each F, from numpy's float64 SVD."""
    U, s, Vt = np.linalg.svd(F.astype(np.float64))
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, 2] *= -1                      # numpy orders singular values: column 2 is the smallest
    return U @ Vt


def angles_degrees(R, Rref):
    cos = np.clip((np.einsum("nij,nij->n", R, Rref) - 1) / 2, -1, 1)
    return np.degrees(np.arccos(cos))


def test_float32_rotations_of_near_degenerate_tets_match_a_float64_svd():
    fem.init("cpu", "f32")
    F = near_degenerate_gradients()
    gradients = ti.Matrix.field(3, 3, ti.f32, COUNT)
    polar, warm = (ti.Matrix.field(3, 3, ti.f32, COUNT) for _ in range(2))
    gradients.from_numpy(F)

    @ti.kernel
    def extract():
        for i in range(COUNT):
            polar[i] = polar_rotation(gradients[i])
            R, _ = rotation_of(gradients[i], ti.Vector([0.0, 0.0, 0.0, 1.0]))   # a start far off
            warm[i] = R

    extract()
    expected = reference_rotations(F)
    for R in (polar.to_numpy(), warm.to_numpy()):
        error = angles_degrees(R.astype(np.float64), expected)
        assert error.max() < 0.1, f"{(error > 0.1).sum()} rotations off, up to {error.max():.3g} degrees"
