"""The coursework's way, as a baseline: assemble K, factorise A, solve (numpy/scipy, float64).

The same backward Euler step as `fem.implicit` (method.md), with the same scene
(masses, materials, Rayleigh damping, gravity, pins, ground, impulses):

    A v_new = M v + dt (f_elastic(x) + M g),   A = cM M + cK K(R),   x_new = x + dt v_new

but K(R) = sum_e R Ke R^T is assembled as a sparse matrix from the textbook
12x12 element matrices and A is factorised: once for linear FEM (A never
changes), every step for corotational FEM (the rotations do). Rotations come
from a numpy SVD, so this module shares no code with the engine's solver and
the two can check each other. It always runs in float64.

A's sparsity pattern is the mesh's and never changes: the rotations change its values, and a
pinned dof clears its row and column but keeps them. The ground is the engine's energy (a
penalty and lagged friction, fem/implicit/effects.py): on a scene with a ground each step
minimises it by Newton's method, refactorising A plus the ground's per-vertex blocks. So a solver that can split
its work analyses the pattern (fill-reducing ordering, symbolic factor) once and only
refactorises the values each step, as a user who knows their solver would. A backend
`B(A)` analyses what it can of A's pattern; `factorise(A)` for A's values, then `solve(b)`;
`factor_bytes` is its factor's size. `BACKENDS`, fastest first:

    pardiso   MKL PARDISO (pypardiso, `pip install ".[fast-direct]"`): Cholesky, analysis once
    cholmod   CHOLMOD (scikit-sparse, if installed): Cholesky, analysis once
    superlu   scipy's SuperLU, always there: LU, ordered and analysed again every step
              (the coursework's way)
"""

import time
import weakref

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fem.builder import initial_state
from fem.implicit.effects import CONTACT_STIFFNESS, RECOVERY_SPEED

try:
    import pypardiso
except ImportError:   # an optional extra; also raised when pypardiso cannot find MKL
    pypardiso = None
try:
    from sksparse import cholmod
except ImportError:
    cholmod = None

BYTES_PER_ENTRY = 12   # a factor entry: float64 value + int32 index


class Pardiso:
    """MKL PARDISO through pypardiso, for a symmetric positive definite A (matrix type 2).

    PARDISO reads only the upper triangle of a symmetric matrix. pypardiso's own `solve`
    would analyse again whenever A's values change, so the three phases are called one by one:
    11 (analysis) here, 22 (numeric factorisation) per `factorise`, 33 (solve) per `solve`.
    """

    label, library = "MKL PARDISO", "pypardiso"
    SPD = 2

    def __init__(self, A):
        rows = np.repeat(np.arange(A.shape[0]), np.diff(A.indptr))
        self.upper = np.flatnonzero(A.indices >= rows)     # A's entries that PARDISO reads
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[self.upper], minlength=A.shape[0]))])
        self.U = sp.csr_matrix((A.data[self.upper], A.indices[self.upper], indptr), shape=A.shape)
        self.pardiso = pypardiso.PyPardisoSolver(mtype=self.SPD)
        weakref.finalize(self, self.pardiso.free_memory, True)   # MKL's memory is not Python's
        self.run(11)
        self.factor_bytes = BYTES_PER_ENTRY * int(self.pardiso.get_iparm(18))   # the analysis counts the entries

    def run(self, phase, b=None):
        """One PARDISO phase on U (pypardiso's documented way to call a phase is its `_call_pardiso`)."""
        self.pardiso.set_phase(phase)
        return self.pardiso._call_pardiso(self.U, np.zeros(self.U.shape[0]) if b is None else b)

    def factorise(self, A):
        np.take(A.data, self.upper, out=self.U.data)
        self.run(22)

    def solve(self, b):
        return self.run(33, b)


class Cholmod:
    """CHOLMOD through scikit-sparse: the ordering and symbolic factor once, a numeric Cholesky per `factorise`."""

    label, library = "CHOLMOD", "scikit-sparse"

    def __init__(self, A):
        self.factor = cholmod.analyze(A.T)            # A is symmetric: A.T is A in CSC, without a copy
        self.factor_bytes = 0                         # known once factorised

    def factorise(self, A):
        self.factor.cholesky_inplace(A.T)
        if not self.factor_bytes:
            self.factor_bytes = BYTES_PER_ENTRY * self.factor.L().nnz

    def solve(self, b):
        return self.factor(b)


class SuperLU:
    """scipy's SuperLU: orders, analyses and factorises from scratch in every `factorise`."""

    label, library = "SuperLU", "scipy"

    def __init__(self, A):
        self.factor_bytes = 0

    def factorise(self, A):
        self.lu = spla.splu(A.T, permc_spec="MMD_AT_PLUS_A")
        self.factor_bytes = BYTES_PER_ENTRY * (self.lu.L.nnz + self.lu.U.nnz)

    def solve(self, b):
        return self.lu.solve(b)


BACKENDS = {"pardiso": Pardiso, "cholmod": Cholmod, "superlu": SuperLU}   # fastest first
INSTALLED = {"pardiso": pypardiso is not None, "cholmod": cholmod is not None, "superlu": True}


def fastest_available():
    """The name of the fastest backend installed here."""
    return next(name for name in BACKENDS if INSTALLED[name])


def shape_gradients(X, tets):
    """g (m, 4, 3): gradients of a tet's four linear shape functions (1/m); W (m,): rest volumes (m^3).

    g_k is row k of Bm = Dm^-1 for k < 3 and g_3 = -(g_0 + g_1 + g_2).
    """
    Dm = np.stack([X[tets[:, k]] - X[tets[:, 3]] for k in range(3)], axis=2)
    Bm = np.linalg.inv(Dm)
    g = np.concatenate([Bm, -Bm.sum(axis=1, keepdims=True)], axis=1)
    return g, np.abs(np.linalg.det(Dm)) / 6


def element_stiffness(g, W, mu, lam):
    """Ke (m, 4, 3, 4, 3): each tet's 12x12 matrix (N/m), rows (corner a, axis i), columns (b, j);
    Ke.reshape(m, 12, 12) is the textbook one. Its 3x3 block between corners a and b is

    Ke_ab = W (lam g_a g_b^T + mu g_b g_a^T + mu (g_a . g_b) I), so that f_a = -sum_b Ke_ab u_b.
    """
    gg = np.einsum("eai,ebi->eab", g, g)
    Ke = (mu[:, None, None, None, None] * np.einsum("ebi,eaj->eaibj", g, g)
          + lam[:, None, None, None, None] * np.einsum("eai,ebj->eaibj", g, g)
          + (mu[:, None, None] * gg)[:, :, None, :, None] * np.eye(3)[:, None, :])
    return W[:, None, None, None, None] * Ke


def polar_rotations(F):
    """R (m, 3, 3): proper rotation nearest to each F, R = U V^T from F = U S V^T.

    A reflection (det U V^T < 0, an inverted tet) is moved into the smallest
    singular value, which numpy puts last (Irving et al. 2004).
    """
    U, _, Vt = np.linalg.svd(F)
    flip = np.linalg.det(U @ Vt) < 0
    U[flip, :, 2] *= -1
    return U @ Vt


class DirectSolver:
    """Steps a `fem.Simulation`'s scene with an assembled, factorised matrix.

    The coursework's step: one linear solve with the rotations frozen, what the engine does
    with `step = "single"`. Reads the engine's model and scene only; its own state is x, v (n, 3) float64 numpy arrays.
    `backend`: a name in `BACKENDS`, by default the fastest installed.
    """

    def __init__(self, sim, backend=None):
        model, effects = sim.model, sim.scene.effects
        self.dt = sim.settings.dt
        self.cM, self.cK = sim.coefficients
        self.effects = effects
        self.tets = model.tets_np
        self.X = model.rest_positions_np
        self.mass = model.mass_np
        n, m = model.n_vertices, model.n_tets
        mu, lam = np.empty(m), np.empty(m)
        self.corotational = np.zeros(m, bool)       # R from F: corotational and naive tets
        self.naive = np.zeros(m, bool)              # f = -R Ke R^T (x - X): the rest shape turns too
        for info in model.bodies:
            E, nu = info.material.E, info.material.nu
            mu[info.tets], lam[info.tets] = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
            self.corotational[info.tets] = info.method != "linear"
            self.naive[info.tets] = info.method == "corotational-naive"
        g, W = shape_gradients(self.X, self.tets)
        self.Ke = element_stiffness(g, W, mu, lam)
        self.Bm = g[:, :3, :]                        # F = Ds Bm
        self.free = model.free_np.astype(bool)
        self.free_dofs = np.repeat(self.free, 3)
        self.impulses = sorted(sim.impulses, key=lambda imp: imp[0])
        self.build_pattern(n)
        self.x, self.v = initial_state(sim.scene, model)
        self.t = 0.0
        self.A = self.system_matrix(self.rotations())
        self.fixed = None                   # the dofs fixed when A was last factorised
        self.backend_name = backend or fastest_available()
        start = time.perf_counter()
        self.backend = BACKENDS[self.backend_name](self.A)   # analyses A's pattern, where it can
        self.analysis_ms = 1e3 * (time.perf_counter() - start)

    def build_pattern(self, n):
        """The sparsity of K, once: where each of the m x 144 element entries lands in a CSR matrix."""
        dofs = (3 * self.tets[:, :, None] + np.arange(3)).reshape(-1, 12)
        rows = np.repeat(dofs, 12, axis=1).ravel()
        cols = np.tile(dofs, (1, 12)).ravel()
        size = 3 * n
        keys, self.slot = np.unique(rows.astype(np.int64) * size + cols, return_inverse=True)
        self.indices = (keys % size).astype(np.int32)
        self.indptr = np.searchsorted(keys // size, np.arange(size + 1)).astype(np.int32)
        self.rows = (keys // size).astype(np.int32)
        self.diagonal = np.flatnonzero(self.rows == self.indices)   # one slot per dof, in dof order
        own = 3 * np.arange(n)[:, None, None]                       # each vertex's own 3x3 block
        self.blocks = np.searchsorted(keys, (own + np.arange(3)[:, None]) * size + own + np.arange(3))
        self.size = size

    def rotations(self):
        """Per-tet R: the polar rotation of F for corotational tets, the identity for linear ones."""
        R = np.broadcast_to(np.eye(3), (len(self.tets), 3, 3)).copy()
        if self.corotational.any():
            x, T = self.x, self.tets[self.corotational]
            Ds = np.stack([x[T[:, k]] - x[T[:, 3]] for k in range(3)], axis=2)
            R[self.corotational] = polar_rotations(Ds @ self.Bm[self.corotational])
        return R

    def system_matrix(self, R):
        """A = cM M + cK sum_e R Ke R^T (3n x 3n CSR), summed into the fixed pattern."""
        KR = np.einsum("eij,eajbk,elk->eaibl", R, self.Ke, R, optimize=True)   # R Ke_ab R^T, every block
        data = self.cK * np.bincount(self.slot, KR.ravel(), minlength=len(self.indices))
        data[self.diagonal] += self.cM * np.repeat(self.mass, 3)
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))

    def constrained(self, fixed, A=None):
        """A (default: self.A) with the rows and columns of fixed dofs cleared but for their
        diagonal: the same pattern."""
        data = (self.A if A is None else A).data.copy()
        data[(fixed[self.rows] | fixed[self.indices]) & (self.rows != self.indices)] = 0
        return sp.csr_matrix((data, self.indices, self.indptr), shape=self.A.shape)

    @property
    def memory_bytes(self):
        """Bytes held by A and its factor."""
        A = self.A
        return A.data.nbytes + A.indices.nbytes + A.indptr.nbytes + self.backend.factor_bytes

    def elastic_forces(self, R):
        """(n, 3) f = sum over tets of -R Ke (R^T x_e - X_e), N (naive tets: -R Ke R^T (x_e - X_e))."""
        xe, Xe = self.x[self.tets], self.X[self.tets]
        m = len(self.tets)
        u = np.einsum("eji,eaj->eai", R, xe) - Xe                          # R^T x_e - X_e
        if self.naive.any():                                               # naive: R^T x_e - R^T X_e
            u[self.naive] += Xe[self.naive] - np.einsum("eji,eaj->eai", R[self.naive], Xe[self.naive])
        Ku = (self.Ke.reshape(m, 12, 12) @ u.reshape(m, 12, 1)).reshape(m, 4, 3)
        fe = -np.einsum("eij,eaj->eai", R, Ku)
        f = np.zeros((len(self.X), 3))
        for k in range(3):
            f[:, k] = np.bincount(self.tets.ravel(), fe[:, :, k].ravel(), minlength=len(self.X))
        return f

    def step(self):
        """One backward Euler step; returns wall_ms, rotation_ms, assembly_ms, factorise_ms, solve_ms."""
        start = time.perf_counter()
        while self.impulses and self.impulses[0][0] <= self.t + 0.5 * self.dt:
            _, ids, dv = self.impulses.pop(0)
            np.add.at(self.v, ids, self.free[ids, None] * np.asarray(dv, float))
        R = self.rotations()
        rotated = time.perf_counter()
        fixed = ~self.free_dofs                    # pinned: v = 0
        corotational = self.corotational.any()
        if corotational:
            self.A = self.system_matrix(R)
        assembled = time.perf_counter()
        ground = self.effects.ground is not None
        if not ground and (corotational or self.fixed is None):
            self.backend.factorise(self.constrained(fixed))   # linear: once
        self.fixed = fixed
        factorised = time.perf_counter()           # on the ground, Newton factorises once per iteration
        f = self.elastic_forces(R)
        if self.effects.gravity is not None:
            f += self.mass[:, None] * np.asarray(self.effects.gravity)
        b = (self.mass[:, None] * self.v + self.dt * f).ravel()
        if ground:
            v_new = self.ground_newton(b, fixed)
        else:
            v_new = self.backend.solve(np.where(fixed, 0.0, b))
        self.v = v_new.reshape(-1, 3)
        self.x = self.x + self.dt * self.v
        self.t += self.dt
        end = time.perf_counter()
        return {"wall_ms": 1e3 * (end - start), "rotation_ms": 1e3 * (rotated - start),
                "assembly_ms": 1e3 * (assembled - rotated), "factorise_ms": 1e3 * (factorised - assembled),
                "solve_ms": 1e3 * (end - factorised)}

    # ---------------------------------------------------------------- the ground, as the engine's energy

    def ground_terms(self, v, plane, normal):
        """The ground's terms of E at velocities v (n, 3) (fem/implicit/effects.py): the penalty
        below each vertex's plane and the lagged friction, J; their gradient (n, 3), N s, and
        Hessian blocks (n, 3, 3), kg/s."""
        k = CONTACT_STIFFNESS / self.dt ** 2 * self.mass
        d = np.minimum(0.0, self.x[:, 1] + self.dt * v[:, 1] - plane)
        grad, hess = np.zeros_like(v), np.zeros((len(v), 3, 3))
        grad[:, 1] = self.dt * k * d
        hess[:, 1, 1] = self.dt ** 2 * k * (d < 0)
        u = v[:, [0, 2]]
        s = np.linalg.norm(u, axis=1)
        eps, lam = self.effects.stick_speed, self.dt * self.effects.friction * normal
        slow = s < eps                                    # IPC's cubic below eps, |u| above
        f0 = np.where(slow, s * s / eps - s ** 3 / (3 * eps * eps), s - eps / 3)
        across = np.where(slow, 2 / eps - s / eps ** 2, 1 / np.maximum(s, eps))     # f1(s) / s
        along = np.where(slow, 2 / eps - 2 * s / eps ** 2, 0.0)                       # f1'(s)
        grad[:, [0, 2]] = (lam * across)[:, None] * u
        t = u / np.maximum(s, 1e-30)[:, None]
        block = (lam * across)[:, None, None] * np.eye(2) \
            + (lam * (along - across))[:, None, None] * t[:, :, None] * t[:, None, :]
        hess[:, 0, 0], hess[:, 0, 2], hess[:, 2, 0], hess[:, 2, 2] = block.reshape(-1, 4).T
        energy = 0.5 * (k * d * d).sum() + (lam * f0).sum()
        return energy, grad, hess

    def ground_newton(self, b, fixed, tolerance=1e-12, iterations=50):
        """The step's v on the ground: the minimiser of E(v) = 1/2 v^T A v - b^T v + the ground's
        terms, by Newton's method with a backtracking line search; A plus the ground's blocks is
        factorised at every iteration (same pattern: the blocks are each vertex's own)."""
        plane = np.minimum(self.effects.ground, self.x[:, 1] + RECOVERY_SPEED * self.dt)
        normal = CONTACT_STIFFNESS / self.dt ** 2 * self.mass * np.maximum(0.0, plane - self.x[:, 1])

        def energy(v):
            e, g, H = self.ground_terms(v.reshape(-1, 3), plane, normal)
            return 0.5 * v @ (self.A @ v) - b @ v + e, np.where(fixed, 0.0, self.A @ v - b + g.ravel()), H

        v = np.zeros(self.size)
        E, g, H = energy(v)
        scale = np.linalg.norm(np.where(fixed, 0.0, b)) + 1e-300
        for _ in range(iterations):
            if np.linalg.norm(g) <= tolerance * scale:
                break
            A = self.A.copy()
            np.add.at(A.data, self.blocks.ravel(), H.ravel())
            self.backend.factorise(self.constrained(fixed, A))
            d = self.backend.solve(-g)
            a = 1.0
            while True:
                E_new, g_new, H_new = energy(v + a * d)
                if E_new <= E + 1e-4 * a * (g @ d) or a < 1e-8:
                    break
                a *= 0.5
            v, E, g, H = v + a * d, E_new, g_new, H_new
        return v
