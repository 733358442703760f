"""fem/quick_ops.py builds Taichi's small-matrix operations without Taichi's per-call translation:
the same numbers, bit for bit, as Taichi's own functions, and Taichi's own errors."""

import numpy as np
import pytest
import taichi as ti

import fem
from fem import quick_ops

N = 64                      # random cases per operation


def kernel_of_every_operation():
    """A kernel using each operation quick_ops covers, on random 2x2, 3x3, 3x2 and 2x3 inputs;
    made anew each time, so that it is translated with whichever functions are installed."""
    A = ti.Matrix.field(3, 3, float, N)
    B = ti.Matrix.field(3, 3, float, N)
    P = ti.Matrix.field(2, 2, float, N)
    R = ti.Matrix.field(3, 2, float, N)
    u = ti.Vector.field(3, float, N)
    w = ti.Vector.field(3, float, N)
    q = ti.Vector.field(2, float, N)
    d = ti.Vector.field(3, ti.f64, N)
    rng = np.random.default_rng(3)
    for field in (A, B, P, R, u, w, q, d):
        field.from_numpy(rng.normal(size=field.to_numpy().shape))
    out = ti.field(ti.f64, (N, 96))

    @ti.kernel
    def run():
        for k in range(N):
            a, b, p, r = A[k], B[k], P[k], R[k]
            x, y, z, e = u[k], w[k], q[k], d[k]
            values = [a @ b, a @ x, x @ a, r @ z, x @ r, a.transpose(), r.transpose(), a.inverse(), p.inverse(),
                      a.determinant(), p.determinant(), a.trace(), a.sum(), x.sum(), a.norm_sqr(), x.norm(),
                      x.norm(1e-3), x.dot(y), x.dot(e), x.cross(y), x.outer_product(z),
                      ti.Matrix.cols([x, y, x + y]), ti.Vector.zero(float, 3), ti.Matrix.zero(float, 2, 3),
                      ti.Matrix.identity(float, 3), x @ y]
            i = 0                               # every number of every value, in turn
            for value in ti.static(values):
                if ti.static(not isinstance(value, ti.lang.expr.Expr) or not value.is_tensor()):
                    out[k, i] = value
                    i += 1
                elif ti.static(len(value.get_shape()) == 1):
                    for j in ti.static(range(value.get_shape()[0])):
                        out[k, i] = value[j]
                        i += 1
                else:
                    for j, m in ti.static(ti.ndrange(*value.get_shape())):
                        out[k, i] = value[j, m]
                        i += 1

    run()
    return out.to_numpy()


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_every_operation_gives_taichis_own_numbers_bit_for_bit(precision):
    fem.init("cpu", precision)                     # installs quick_ops
    quick = kernel_of_every_operation()
    quick_ops.uninstall()
    try:
        taichi = kernel_of_every_operation()
    finally:
        quick_ops.install()
    assert np.isfinite(quick).all() and np.count_nonzero(quick) > 60 * N
    assert np.array_equal(quick.view(np.uint64), taichi.view(np.uint64))


def test_a_wrong_shape_gets_taichis_own_error(f32):
    a = ti.Matrix.field(3, 3, float, ())
    z = ti.Vector.field(2, float, ())

    @ti.kernel
    def wrong():
        print(a[None] @ z[None])

    with pytest.raises(ti.TaichiCompilationError, match="dimension mismatch"):
        wrong()


def test_python_scope_matrices_are_taichis_own(f32):
    a = ti.Matrix([[1.0, 2.0], [3.0, 4.0]])
    assert np.allclose((a @ a).to_numpy(), [[7, 10], [15, 22]])
    assert np.allclose(a.transpose().to_numpy(), [[1, 3], [2, 4]]) and np.isclose(a.sum(), 10.0)
