"""The coarse level of the two-level preconditioner: patches of a body that move rigidly.

Block Jacobi sees one vertex at a time. An error that is smooth over the whole body (a bar
bending, a body turning) is corrected only a vertex's width per CG iteration, so iteration
counts grow with the mesh's size and its stiffness. A coarse level sees those errors whole:

    z = P r = D^-1 r + Q A_c^-1 Q^T r          (additive two-level Schwarz)

D: the 3x3 diagonal blocks of H (block Jacobi). Q: the rigid motions of patches of the
mesh. Each body's vertices are split into patches of about PATCH_VERTICES vertices by
recursive coordinate bisection; a patch a has 6 coarse dofs, a velocity t_a and a spin w_a,
and moves vertex i of it by

    u_i = R_a (t_a + w_a x Y_i),     Y_i = X_i - C_a (rest offset from the patch's centre)

(pinned vertices do not move). These are the rigid-body modes that smoothed aggregation
builds elasticity's coarse spaces from (Vanek, Mandel and Brezina 1996). R_a is the patch's
best-fit rotation, so the patch's motions follow a spinning body.

A_c = Q0^T H0 Q0 is H at rest (R = I, no twist term) seen by the patches at rest (Q0:
R_a = I): the same matrix in every patch's frame, made once per materials and dt, in
float64, and kept as a dense inverse. In a rotated patch, R_a A_c R_a^T is the exact Galerkin
matrix of a body that moved rigidly; a body that also deforms gets a nearby matrix. Either
way P stays symmetric positive definite, which is all PCG needs: the coarse level changes
how many iterations a solve takes, never what it converges to.
"""

import numpy as np
import taichi as ti

from fem import runtime
from fem.reduce import SegmentSums
from fem.rotation import newton_rotation, quaternion_matrix

PATCH_VERTICES = 90      # vertices per patch, about (measured on box50k: 90 to 300 per patch, 128 to 32 patches)
MAX_PATCHES = 128        # patches of all bodies together at most: the coarse matrix is at most 768 x 768
ROTATION_STEPS = 8       # Newton steps per step on a patch's rotation, from the last one
COARSE_PARTS = 8         # on a GPU: each row of the coarse product in this many pieces, a thread each


def split(ids, X, parts):
    """Recursive coordinate bisection: ids (vertex indices) in `parts` groups of about equal
    size, each cut across the longest side of its group's bounding box. Returns a list of arrays."""
    if parts == 1:
        return [ids]
    P = X[ids]
    order = ids[np.argsort(P[:, np.argmax(P.max(0) - P.min(0))], kind="stable")]
    left = parts // 2
    cut = len(order) * left // parts
    return split(order[:cut], X, left) + split(order[cut:], X, parts - left)


def patches(X, bodies, max_patches=MAX_PATCHES):
    """(n,) patch of every vertex: each body in about n_b / PATCH_VERTICES patches (at least one),
    fewer when the bodies together would have more than max_patches."""
    sizes = np.array([b.vertices.stop - b.vertices.start for b in bodies])
    wanted = np.maximum(1, np.round(sizes / PATCH_VERTICES)).astype(int)
    while wanted.sum() > max_patches and wanted.max() > 1:
        wanted = np.maximum(1, wanted // 2)
    if wanted.sum() > max_patches:
        raise ValueError(f"{len(bodies)} bodies need more than {max_patches} patches")
    patch = np.empty(len(X), np.int32)
    first = 0
    for body, parts in zip(bodies, wanted):
        ids = np.arange(body.vertices.start, body.vertices.stop)
        for group in split(ids, X, min(parts, len(ids))):
            patch[group] = first
            first += 1
    return patch


def shape_gradients(X, T):
    """(m, 4, 3) gradients of the four linear shape functions of every tet, and (m,) volumes."""
    Dm = np.stack([X[T[:, k]] - X[T[:, 3]] for k in range(3)], axis=2)
    Bm = np.linalg.inv(Dm)                     # rows: gradients of corners 0, 1, 2
    g = np.concatenate([Bm, -Bm.sum(axis=1, keepdims=True)], axis=1)
    return g, np.abs(np.linalg.det(Dm)) / 6


def centres(X, patch, mass):
    """(patches, 3) the patches' mass-weighted rest centres C_a."""
    count = patch.max() + 1
    weight = np.bincount(patch, mass, count)
    return np.stack([np.bincount(patch, mass * X[:, d], count) for d in range(3)], axis=1) / weight[:, None]


def rigid_modes(X, patch, mass, free):
    """Phi (n, 3, 6): u_i = Phi_i (t, w) = t + w x Y_i for free vertices, 0 for pinned ones;
    and the patches' mass-weighted rest centres C (patches, 3)."""
    C = centres(X, patch, mass)
    Y = X - C[patch]
    Phi = np.zeros((len(X), 3, 6))
    Phi[:, :, :3] = np.eye(3)
    Phi[:, 0, 4], Phi[:, 0, 5] = Y[:, 2], -Y[:, 1]          # w x Y = -[Y]x w
    Phi[:, 1, 3], Phi[:, 1, 5] = -Y[:, 2], Y[:, 0]
    Phi[:, 2, 3], Phi[:, 2, 4] = Y[:, 1], -Y[:, 0]
    return Phi * free[:, None, None], C


def coarse_matrices(X, T, mass, free, patch, chunk=8192):
    """(M_c, K_mu, K_lam) (6 patches square, float64): Q0^T M Q0, and Q0^T K0 Q0 for mu = 1, lam = 0
    and for mu = 0, lam = 1. K0 is linear in mu and lam, and no tet joins two bodies, so a body's
    materials only scale its own rows and columns (`Patches.refresh`).

    K0's 3x3 block of corners a, b of a tet is W (mu (g_a . g_b) I + mu g_b g_a^T + lam g_a g_b^T)
    (method.md); each block reaches the coarse matrix as Phi_a^T K_ab Phi_b, tets in chunks."""
    count = patch.max() + 1
    Phi, _ = rigid_modes(X, patch, mass, free)
    parts = np.zeros((2, count * count, 6, 6))
    for s in range(0, len(T), chunk):
        t = T[s:s + chunk]
        g, W = shape_gradients(X, t)
        dots = np.einsum("mai,mbi->mab", g, g)
        K_mu = dots[..., None, None] * np.eye(3) + np.einsum("mbi,maj->mabij", g, g)
        K_lam = np.einsum("mai,mbj->mabij", g, g)
        keys = (patch[t][:, :, None] * count + patch[t][:, None, :]).ravel()
        Pe = Phi[t]                                               # (m, 4, 3, 6)
        for part, Kab in zip(parts, (K_mu, K_lam)):
            blocks = np.einsum("maip,mabij,mbjq->mabpq", Pe, W[:, None, None, None, None] * Kab, Pe,
                               optimize=True).reshape(-1, 36)
            for pq in range(36):
                part[:, pq // 6, pq % 6] += np.bincount(keys, blocks[:, pq], count * count)
    K_mu, K_lam = (p.reshape(count, count, 6, 6).transpose(0, 2, 1, 3).reshape(6 * count, 6 * count)
                   for p in parts)
    Mb = np.zeros((count, 6, 6))
    np.add.at(Mb, patch, mass[:, None, None] * np.einsum("nip,niq->npq", Phi, Phi))
    M = np.zeros((count, 6, count, 6))
    M[np.arange(count), :, np.arange(count), :] = Mb                     # block diagonal
    return M.reshape(6 * count, 6 * count), 0.5 * (K_mu + K_mu.T), 0.5 * (K_lam + K_lam.T)


def inverse(A):
    """The inverse of the symmetric positive semi-definite A, scaled to a unit diagonal first.
    Rows that are all zero (patches of pinned vertices only) stay zero; where round-off has
    made A numerically singular (a huge dt), the pseudo-inverse of its well-defined part."""
    import scipy.linalg   # here, not at the top: its import is 0.14 s of every start, and small scenes never need it
    used = np.diag(A) > 0
    scale = 1.0 / np.sqrt(np.diag(A)[used])
    B = A[np.ix_(used, used)] * scale[:, None] * scale[None, :]
    try:
        inner = scipy.linalg.cho_solve(scipy.linalg.cho_factor(B), np.eye(len(B)))
    except np.linalg.LinAlgError:
        values, vectors = np.linalg.eigh(B)
        keep = values > 1e-12 * values.max()
        inner = (vectors[:, keep] / values[keep]) @ vectors[:, keep].T
    out = np.zeros_like(A)
    out[np.ix_(used, used)] = scale[:, None] * inner * scale[None, :]
    return 0.5 * (out + out.T)


@ti.data_oriented
class Patches:
    """The coarse level's fields and the passes of one preconditioner application.

    Fields (p patches in use of `capacity`):
        patch (n,), members (n,), start (p+1,)   vertex -> patch, and each patch's vertices
            (members[start[a]:start[a+1]]: the patches are ranges of members, not of vertex
            numbers, which stay the model's: outputs, pins and stats name vertices by them)
        centre (p, 3)              C_a, m
        spread_inverse (p, 3x3)    (sum m Y Y^T)^-1 of the patch at rest, 1/(kg m^2)
        rotates (p,)               1: R_a follows the body (corotational), 0: R_a = I
        quaternion (p, 4), frame (p, 3x3)   R_a
        coarse_inverse (6p, 6p)    A_c^-1
        g (6p,)                    Q^T r
        y (parts, 6p)              A_c^-1 Q^T r, in `parts` pieces that add up to it (one on a CPU)
    """

    def __init__(self, model, serial):
        n, capacity = model.capacity.vertices, self.fitting(model.capacity)
        self.model, self.capacity = model, capacity
        self.serial = serial                  # the solver's vertex loops run on one thread: these too
        self.patch = ti.field(ti.i32, n)
        self.members = ti.field(ti.i32, n)
        self.start = ti.field(ti.i32, capacity + 1)
        self.centre = ti.Vector.field(3, float, capacity)
        self.spread_inverse = ti.Matrix.field(3, 3, float, capacity)
        self.rotates = ti.field(ti.i32, capacity)
        self.quaternion = ti.Vector.field(4, float, capacity)
        self.frame = ti.Matrix.field(3, 3, float, capacity)
        self.coarse_inverse = ti.field(float, (6 * capacity, 6 * capacity))
        self.parts = 1 if serial or runtime.on_cpu() else COARSE_PARTS
        self.g = ti.field(float, 6 * capacity)
        self.y = ti.field(float, (self.parts, 6 * capacity))
        self.count = ti.field(ti.i32, ())
        self.sums = SegmentSums(n, capacity, 6, serial=serial)   # Q^T r, per patch
        self.frame_sums = SegmentSums(n, capacity, 9, serial=serial)    # sum m y Y^T, per patch
        self.key = None

    @staticmethod
    def fitting(capacity):
        """Room for the patches of a model of this capacity: PATCH_VERTICES each, up to MAX_PATCHES,
        and at least one per body."""
        wanted = 1 << max(0, -(-capacity.vertices // PATCH_VERTICES) - 1).bit_length()
        return max(capacity.bodies, min(MAX_PATCHES, wanted))

    def load(self):
        """Split the model's bodies into patches (a new scene)."""
        model = self.model
        X, mass = model.rest_positions_np, model.mass_np
        patch = patches(X, model.bodies, self.capacity)
        count = int(patch.max()) + 1
        self.patch_np, self.count[None] = patch, count
        C = centres(X, patch, mass)
        Y = X - C[patch]
        spread = np.zeros((count, 3, 3))
        np.add.at(spread, patch, mass[:, None, None] * np.einsum("ni,nj->nij", Y, Y))
        members = np.argsort(patch, kind="stable")
        start = np.searchsorted(patch[members], np.arange(count + 1))
        write, cap = model.write, self.capacity
        write(self.patch, patch)
        write(self.members, members)
        write(self.start, model.padded(start, cap + 1, np.int32, pad=start[-1]))
        self.sums.load(start)
        self.frame_sums.load(start)
        write(self.centre, C)
        write(self.spread_inverse, np.linalg.pinv(spread))
        self.patch_body = model.vertex_body_np[members[start[:-1]]]   # the body of each patch
        self.key, self.matrices = None, None
        self.reset()

    def reset(self):
        self.quaternion.from_numpy(np.tile([0.0, 0.0, 0.0, 1.0], (self.capacity, 1)))
        self.frame.from_numpy(np.tile(np.eye(3), (self.capacity, 1, 1)))

    def refresh(self, cM, cK):
        """A_c^-1 for H = cM M + cK K0, when the materials, methods or dt changed: the patches'
        matrices once per scene, then a weighted sum and a dense inverse."""
        model = self.model
        key = (model.version, cM, cK)
        if key == self.key:
            return
        size = 6 * (self.capacity - self.count[None])
        model.write(self.coarse_inverse, np.pad(inverse(self.coarse_matrix(cM, cK)), ((0, size), (0, size))))
        if self.key is None or self.key[0] != model.version:      # R_a follows corotational bodies only
            model.write(self.rotates, np.array([model.bodies[b].method != "linear" for b in self.patch_body],
                                               np.int32))
            self.reset()
        self.key = key

    def coarse_matrix(self, cM, cK):
        """A_c = Q0^T (cM M + cK K0) Q0 with the bodies' current materials (float64)."""
        model = self.model
        if self.matrices is None:
            self.matrices = coarse_matrices(model.rest_positions_np, model.tets_np, model.mass_np,
                                            model.free_np.astype(np.float64), self.patch_np)
        M, K_mu, K_lam = self.matrices
        lame = [model.bodies[b].material.lame for b in self.patch_body]
        mu, lam = (np.sqrt(np.repeat(values, 6)) for values in zip(*lame))   # a body's rows and columns
        return cM * M + cK * (mu[:, None] * K_mu * mu[None, :] + lam[:, None] * K_lam * lam[None, :])

    @ti.kernel
    def update_frames(self, x: ti.template()):
        """R_a <- the rotation of the patch's best-fit deformation F = (sum m y Y^T)(sum m Y Y^T)^-1,
        by Newton steps from the last R_a (any rotation will do for a preconditioner; the steps
        just keep it close). y is x less any point: sum m Y = 0, so the patch's first member
        will do as well as its centre, and the sum takes one pass, in two stages (fem/reduce.py)."""
        self.frame_sums.reduce(self.spread, self.store_frame, x)

    @ti.func
    def spread(self, j, a, x: ti.template()):
        """Member j's m y Y^T (row by row), i = members[j], y = x_i less the patch's first member."""
        i = self.members[j]
        S = self.model.mass[i] * (x[i] - x[self.members[self.start[a]]]).outer_product(
            self.model.rest_positions[i] - self.centre[a])
        return ti.Vector([S[0, 0], S[0, 1], S[0, 2], S[1, 0], S[1, 1], S[1, 2], S[2, 0], S[2, 1], S[2, 2]])

    @ti.func
    def store_frame(self, a, S, x: ti.template()):
        if self.rotates[a]:
            F = ti.Matrix([[S[0], S[1], S[2]], [S[3], S[4], S[5]], [S[6], S[7], S[8]]]) @ self.spread_inverse[a]
            q, _ = newton_rotation(F, self.quaternion[a], ROTATION_STEPS)
            self.quaternion[a] = q
            self.frame[a] = quaternion_matrix(q)

    @ti.func
    def restrict(self, r: ti.template(), on):
        """g <- Q^T r: per patch, the sum of R_a^T r_i and of Y_i x R_a^T r_i (force and torque),
        in two stages over the patch's members (fem/reduce.py): a patch of a large mesh has
        thousands of vertices, too many for one thread."""
        self.sums.reduce(self.moment, self.store_moment, r, on)

    @ti.func
    def moment(self, j, a, r: ti.template()):
        """Member j's (R_a^T r_i, Y_i x R_a^T r_i), i = members[j], of patch a."""
        i = self.members[j]
        f = self.frame[a].transpose() @ r[i]
        torque = (self.model.rest_positions[i] - self.centre[a]).cross(f)
        return ti.Vector([f[0], f[1], f[2], torque[0], torque[1], torque[2]])

    @ti.func
    def store_moment(self, a, moment, r: ti.template()):
        for k in ti.static(range(6)):
            self.g[6 * a + k] = moment[k]

    @ti.func
    def solve(self, on):
        """y <- A_c^-1 g, a dense product. On a CPU a row per thread. On a GPU a row is too long
        for one thread (768 serial loads): each row in `parts` pieces, a thread each, and
        neighbouring threads take neighbouring rows of one piece. A_c^-1 is symmetric, so a
        thread reads its row as a column, and the loads of neighbouring threads coalesce."""
        size = 6 * self.count[None]
        width = (size + self.parts - 1) // self.parts
        threads = size * self.parts * on
        ti.loop_config(serialize=self.serial)
        for t in range(6 * self.capacity * self.parts if ti.static(self.sums.capacity_loops) else threads):
            if t >= threads:
                continue
            row, part = t % size, t // size
            s = 0.0
            for col in range(part * width, ti.min(size, part * width + width)):
                if ti.static(self.parts > 1):
                    s += self.coarse_inverse[col, row] * self.g[col]
                else:
                    s += self.coarse_inverse[row, col] * self.g[col]
            self.y[part, row] = s

    @ti.func
    def prolong(self, i):
        """(Q y)_i = R_a (t_a + w_a x Y_i), a = vertex i's patch (before filtering); y's pieces added."""
        a = self.patch[i]
        t, w = ti.Vector.zero(float, 3), ti.Vector.zero(float, 3)
        for part in ti.static(range(self.parts)):
            t += ti.Vector([self.y[part, 6 * a], self.y[part, 6 * a + 1], self.y[part, 6 * a + 2]])
            w += ti.Vector([self.y[part, 6 * a + 3], self.y[part, 6 * a + 4], self.y[part, 6 * a + 5]])
        return self.frame[a] @ (t + w.cross(self.model.rest_positions[i] - self.centre[a]))
