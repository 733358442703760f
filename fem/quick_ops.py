"""Taichi's small-matrix operations, built straight from Python instead of translated at each use.

Taichi 1.7 writes `A @ B`, `A.transpose()`, `u.dot(w)`, `u.cross(w)`, `u.norm()`, `A.inverse()`,
`ti.Matrix.cols(...)` and `ti.Vector.zero(...)` as Taichi functions (taichi/lang/matrix_ops.py)
that its frontend walks again, node by node, at every call in every kernel, on every start, even
when the offline cache then supplies the compiled kernel: about half of the time a start spends
translating kernels (docs/benchmark.md, "Where a warm start goes"). Here each builds the same
arithmetic, in the same order, with the same calls Taichi's walk ends in:

    Taichi's matmul (a 3x3 A @ B)                  here
    z = zero matrix (A[0,0] * B[0,0] * 0)          z_ij = ((zero + A_i0 B_0j) + A_i1 B_1j) + A_i2 B_2j
    for i, j, k: z[i, j] = z[i, j] + A[i,k] B[k,j]

Arguments are held in local variables, as Taichi holds an inlined function's arguments, and
what Taichi returns in a variable (a product, a sum) is returned in one. Anything else (a
matrix in Python scope, a shape these do not cover, a shape that is wrong) goes to Taichi's own
function, which also gives Taichi's own error.
"""

from taichi._lib import core as _ti_core
from taichi.lang import impl, matrix_ops, ops
from taichi.lang.expr import Expr, make_expr_group
from taichi.lang.matrix import make_matrix

_taichi = {}                     # name -> Taichi's own function, once installed


def install():
    """Replace Taichi's functions by these (once per process)."""
    if _taichi:
        return
    for name, quick in QUICK.items():
        _taichi[name] = getattr(matrix_ops, name)
        setattr(matrix_ops, name, _either(name, quick))


def uninstall():
    """Taichi's own functions again (a test compares the two)."""
    for name, taichi_op in _taichi.items():
        setattr(matrix_ops, name, taichi_op)
    _taichi.clear()


def _either(name, quick):
    def op(*args, **kwargs):
        if impl.inside_kernel():
            result = quick(*args, **kwargs)
            if result is not NotImplemented:
                return result
        return _taichi[name](*args, **kwargs)
    op.__name__ = op.__qualname__ = name
    op.__module__ = matrix_ops.__name__      # Taichi's own, in its place: no "non-taichi function" warning
    return op


def _shape(x, ndim):
    """x's shape when x is a Taichi tensor expression with ndim axes, else None."""
    if isinstance(x, Expr) and x.is_tensor():
        shape = tuple(x.get_shape())
        if len(shape) == ndim:
            return shape
    return None


def _held(x):
    """x in a local variable, as Taichi binds an inlined function's argument."""
    return impl.expr_init(x)


def _at(x, *index):
    """x[index] of a tensor expression (impl.subscript's own path for one, unchecked)."""
    builder = impl.get_runtime().compiling_callable.ast_builder()
    info = _ti_core.DebugInfo(impl.get_runtime().get_current_src_info())
    return Expr(builder.expr_subscript(x.ptr, make_expr_group(*index), info))


def _added(terms):
    """((t0 + t1) + t2) + ...: Taichi's `_reduce` with add."""
    total = terms[0]
    for term in terms[1:]:
        total = ops.add(total, term)
    return total


def matmul(x, y):
    if _shape(x, 1) and _shape(y, 1):
        return dot(x, y)
    if _shape(x, 1) and _shape(y, 2):                  # v @ M = M^T v, as Taichi takes it
        return _matrix_vector(y, x, lambda m, i, k: _at(m, k, i), *reversed(_shape(y, 2)), _shape(x, 1)[0])
    if _shape(x, 2) and _shape(y, 1):
        return _matrix_vector(x, y, _at, *_shape(x, 2), _shape(y, 1)[0])
    if _shape(x, 2) and _shape(y, 2):
        (rows, inner), (n, cols) = _shape(x, 2), _shape(y, 2)
        if inner != n:
            return NotImplemented
        x, y = _held(x), _held(y)
        zero = _held(_at(x, 0, 0) * _at(y, 0, 0) * 0)
        return _held(make_matrix([[_added([zero] + [_at(x, i, k) * _at(y, k, j) for k in range(inner)])
                                   for j in range(cols)] for i in range(rows)]))
    return NotImplemented


def _matrix_vector(m, v, entry, rows, inner, n):
    """z_i = zero + sum_k entry(m, i, k) v_k (Taichi's matrix-vector loop), entry: m's (i, k) or (k, i)."""
    if inner != n:
        return NotImplemented
    m, v = _held(m), _held(v)
    zero = _held(entry(m, 0, 0) * _at(v, 0) * 0)
    return _held(make_matrix([_added([zero] + [entry(m, i, k) * _at(v, k) for k in range(inner)])
                              for i in range(rows)]))


def transpose(x):
    shape = _shape(x, 2)
    if shape is None:
        return NotImplemented
    x = _held(x)
    return make_matrix([[_at(x, i, j) for i in range(shape[0])] for j in range(shape[1])])


def _indices(shape):
    if len(shape) == 1:
        return [(i,) for i in range(shape[0])]
    return [(i, j) for i in range(shape[0]) for j in range(shape[1])]


def sum(x):                                            # noqa: A001 (Taichi's name)
    shape = _shape(x, 1) or _shape(x, 2)
    if shape is None:
        return NotImplemented
    x = _held(x)
    return _held(_added([_at(x, *index) for index in _indices(shape)]))


def norm_sqr(x):
    shape = _shape(x, 1) or _shape(x, 2)
    if shape is None:
        return NotImplemented
    x = _held(x)
    return _held(_added([_at(x, *index) * _at(x, *index) for index in _indices(shape)]))


def norm(x, eps=0.0):
    squared = norm_sqr(x)
    if squared is NotImplemented:
        return NotImplemented
    return ops.sqrt(squared + _held(eps))            # Taichi holds eps, an argument, too


def dot(x, y):
    if _shape(x, 1) is None or _shape(x, 1) != _shape(y, 1):
        return NotImplemented
    x, y = _held(x), _held(y)
    return _held(_added([_at(x, i) * _at(y, i) for i in range(_shape(x, 1)[0])]))


def cross(x, y):
    if _shape(x, 1) != (3,) or _shape(y, 1) != (3,):
        return NotImplemented
    x, y = _held(x), _held(y)
    return make_matrix([_at(x, 1) * _at(y, 2) - _at(x, 2) * _at(y, 1),
                        _at(x, 2) * _at(y, 0) - _at(x, 0) * _at(y, 2),
                        _at(x, 0) * _at(y, 1) - _at(x, 1) * _at(y, 0)])


def outer_product(x, y):
    if _shape(x, 1) is None or _shape(y, 1) is None:
        return NotImplemented
    (n,), (m,) = _shape(x, 1), _shape(y, 1)
    x, y = _held(x), _held(y)
    return make_matrix([[_at(x, i) * _at(y, j) for j in range(m)] for i in range(n)])


def trace(x):
    shape = _shape(x, 2)
    if shape is None or shape[0] != shape[1]:
        return NotImplemented
    x = _held(x)
    return _held(_added([_at(x, i, i) for i in range(shape[0])]))


def _determinant_of(m, n):
    """det of the held n x n matrix m (n = 2 or 3), term for term as Taichi writes it."""
    if n == 2:
        return _at(m, 0, 0) * _at(m, 1, 1) - _at(m, 0, 1) * _at(m, 1, 0)
    a = lambda i, j: _at(m, i, j)                      # noqa: E731
    return (a(0, 0) * (a(1, 1) * a(2, 2) - a(2, 1) * a(1, 2))
            - a(1, 0) * (a(0, 1) * a(2, 2) - a(2, 1) * a(0, 2))
            + a(2, 0) * (a(0, 1) * a(1, 2) - a(1, 1) * a(0, 2)))


def determinant(x):
    shape = _shape(x, 2)
    if shape not in ((2, 2), (3, 3)):
        return NotImplemented
    return _determinant_of(_held(x), shape[0])


def inverse(x):
    shape = _shape(x, 2)
    if shape not in ((2, 2), (3, 3)):
        return NotImplemented
    m = _held(x)
    inv_determinant = _held(1.0 / _determinant_of(_held(m), shape[0]))
    if shape == (2, 2):
        return inv_determinant * make_matrix([[_at(m, 1, 1), -_at(m, 0, 1)], [-_at(m, 1, 0), _at(m, 0, 0)]])
    e = lambda i, j: _at(m, i % 3, j % 3)              # noqa: E731 (Taichi's E)
    return inv_determinant * make_matrix([[e(i + 1, j + 1) * e(i + 2, j + 2) - e(i + 2, j + 1) * e(i + 1, j + 2)
                                           for i in range(3)] for j in range(3)])


def cols(columns):
    if not isinstance(columns, (list, tuple)) or not columns:
        return NotImplemented
    shapes = {_shape(c, 1) for c in columns}
    if len(shapes) != 1 or None in shapes:
        return NotImplemented
    (n,) = shapes.pop()
    held = [_held(c) for c in columns]
    return make_matrix([[_at(c, i) for c in held] for i in range(n)])


def _filled_vector(n, dtype, val):
    if not isinstance(n, int):
        return NotImplemented
    return make_matrix([val for _ in range(n)], dtype)


def _filled_matrix(n, m, dtype, val):
    if not isinstance(n, int) or not isinstance(m, int):
        return NotImplemented
    return make_matrix([[val for _ in range(m)] for _ in range(n)], dtype)


def _identity_matrix(n, dtype):
    if not isinstance(n, int):
        return NotImplemented
    return make_matrix([[i == j for j in range(n)] for i in range(n)], dtype)


QUICK = {"matmul": matmul, "transpose": transpose, "sum": sum, "norm_sqr": norm_sqr, "norm": norm,
         "dot": dot, "cross": cross, "outer_product": outer_product, "trace": trace,
         "determinant": determinant, "inverse": inverse, "cols": cols, "_filled_vector": _filled_vector,
         "_filled_matrix": _filled_matrix, "_identity_matrix": _identity_matrix}
