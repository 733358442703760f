"""PCG's preconditioner: block Jacobi, plus the coarse level of fem/coarse.py on large meshes.

Block Jacobi keeps the inverse 3x3 diagonal blocks of H = cM M + cK K(R) (plus the ground's
own block, fem/implicit/effects.py), built from every corner around a vertex; the two-level preconditioner adds the rigid patches' correction,

    z = P r = D^-1 r + Q A_c^-1 Q^T r          (fem/coarse.py),

and "auto" picks it from TWO_LEVEL_VERTICES up, where it wins (docs/benchmark.md).

The blocks follow the tets' rotations. PCG only needs them close: in the one-solve step they
are rebuilt once some tet turned STALE_TURN since they were built. Newton's twist stiffness
changes with the stretch, and Jacobi iteration's weight needs the exact blocks: those rebuild
every step. On linear bodies H never changes: built once per dt and materials.

Fields (n vertices of the capacity):
    block_inverse (n, 6)   D_i^-1, symmetric: (xx, xy, xz, yy, yz, zz)
"""

import numpy as np
import taichi as ti

from fem.coarse import Patches
from fem.elastic import stiffness_block

TWO_LEVEL_VERTICES = 2000   # "auto": below, block Jacobi is as fast (its iterations cost less; measured)
STALE_TURN = 0.2            # rad: the blocks are rebuilt once some tet turned this far


@ti.data_oriented
class Preconditioner:
    """Block Jacobi and the coarse level for one model; the blocks use `rotations`' Bm R^T and
    twist, the constraints of `effects`, and skip a sleeping body (`sleep`)."""

    def __init__(self, model, rotations, effects, sleep, switches):
        self.model, self.rotations, self.effects, self.sleep = model, rotations, effects, sleep
        self.serial_tets, self.serial_vertices = switches.serial_tets, switches.serial_vertices
        self.block_inverse = ti.Vector.field(6, float, model.capacity.vertices)
        self.patches = None                                   # the coarse level, made on first use

    def load(self):
        """A new scene: nothing built yet."""
        self.key = None                                       # (cM, cK) the blocks are for; None: stale
        self.turned = 0.0
        self.patches_loaded = False

    def rebuild(self):
        """The next step builds the blocks (a body woke, materials or dt changed)."""
        self.key = None

    def forget(self):
        """The blocks are for other rotations: the next step builds them."""
        self.key = None
        self.turned = 0.0                                     # rad: most any tet turned since they were built

    def reset(self):
        self.forget()
        if self.patches is not None:
            self.patches.reset()

    @staticmethod
    def kind(settings, n_vertices):
        """The preconditioner in use: "two-level" or "jacobi" (block Jacobi); None for Jacobi iteration."""
        if settings.method != "pcg":
            return None
        if settings.preconditioner == "auto":
            return "two-level" if n_vertices >= TWO_LEVEL_VERTICES else "jacobi"
        return settings.preconditioner

    def update(self, x, cM, cK, turned, corotational, exact, reuse, two_level):
        """Ready for this step's H = cM M + cK K(R) at positions x.
        turned: rad, the largest turn of a tet since the last step (Rotations.update).
        exact: rebuild the blocks of corotational bodies every step (Newton, Jacobi iteration).
        reuse: later steps may keep the blocks built now (not so Newton's, which carry its twist)."""
        self.turned += turned
        stale = corotational and (exact or self.turned > STALE_TURN)
        if stale or self.key != (cM, cK):
            self.build_preconditioner(cM, cK)
            self.key = (cM, cK) if reuse else None
            self.turned = 0.0
        if two_level:
            self.prepare_patches(x, cM, cK, corotational)

    def exact_blocks(self, cM, cK):
        """(n, 3, 3) numpy D^-1 built now (Jacobi iteration's weight); the next step builds its own."""
        self.build_preconditioner(cM, cK)
        self.key = None
        return self.block_inverses()

    def prepare_patches(self, x, cM, cK, corotational):
        """The coarse level for this step: patches split once per scene, A_c^-1 once per
        materials and dt, the patches' rotations at x every corotational step."""
        if self.patches is None:
            self.patches = Patches(self.model, self.serial_vertices)
        if not self.patches_loaded:
            self.patches.load()
            self.patches_loaded = True
        self.patches.refresh(cM, cK)
        if corotational:
            self.patches.update_frames(x)

    @ti.kernel
    def build_preconditioner(self, cM: float, cK: float):
        """block_inverse <- inverse of the 3x3 diagonal blocks of H = cM M + cK K(R)."""
        self.build_blocks(cM, cK)

    @ti.func
    def build_blocks(self, cM, cK):
        """`build_preconditioner`'s pass, for a kernel that starts a solve (LinearSolver.start_residual).
        A loop over vertices with the work of a loop over tets (every corner): threaded like one."""
        ti.loop_config(serialize=self.serial_tets)
        for i in range(self.model.vertex_count[None]):
            if not self.sleep.awake[self.model.vertex_body[i]]:      # filtered to 0 while asleep
                continue
            # a pinned vertex keeps an identity block, so the inverse exists even where mass is 0
            block = (cM * self.model.mass[i] + 1.0 - self.model.free[i]) * ti.Matrix.identity(float, 3)
            for j in range(self.model.adjacency_start[i], self.model.adjacency_start[i + 1]):
                slot = self.model.adjacency[j]
                e, k = slot // 4, slot % 4
                B = self.rotations.rotated_Bm[e]
                h = -(B[0, :] + B[1, :] + B[2, :])       # rotated shape gradient of corner k
                if k < 3:
                    h = B[k, :]
                W = self.model.rest_volume[e]
                block += cK * (stiffness_block(h, W, self.model.mu(e), self.model.lam(e))
                               + 0.5 * W * self.rotations.twist[e] * (h.dot(h) * ti.Matrix.identity(float, 3)
                                                                      - h.outer_product(h)))
            if ti.static(self.effects.has_ground):
                block += self.effects.contact_block(i)
            if ti.static(self.effects.has_contact):
                block += self.effects.contact.block[i]
            inv = block.inverse()
            self.block_inverse[i] = ti.Vector([inv[0, 0], inv[0, 1], inv[0, 2],
                                               inv[1, 1], inv[1, 2], inv[2, 2]])

    @ti.func
    def jacobi(self, i, r):
        """D_i^-1 r: vertex i's inverse diagonal block of H times r."""
        s = self.block_inverse[i]
        return ti.Vector([s[0] * r[0] + s[1] * r[1] + s[2] * r[2],
                          s[1] * r[0] + s[3] * r[1] + s[4] * r[2],
                          s[2] * r[0] + s[4] * r[1] + s[5] * r[2]])

    def block_inverses(self):
        """(n, 3, 3) numpy: every vertex's D_i^-1 (for checks and tests)."""
        s = self.block_inverse.to_numpy()[:self.model.n_vertices].astype(np.float64)
        return s[:, [[0, 1, 2], [1, 3, 4], [2, 4, 5]]]

    @ti.func
    def two_level_precondition(self, r: ti.template(), z: ti.template(), on):
        """z <- filtered(D^-1 r + Q A_c^-1 Q^T r): block Jacobi plus the coarse level's correction
        (fem/coarse.py), three passes; returns r.z. `on` = 0 loops over nothing."""
        self.patches.restrict(r, on)
        self.patches.solve(on)
        rz = 0.0
        vertices = self.model.vertex_count[None] * on
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.capacity.vertices if ti.static(self.patches.sums.capacity_loops) else vertices):
            if i >= vertices:
                continue
            ri = r[i]
            zi = self.effects.filtered(i, self.jacobi(i, ri) + self.patches.prolong(i))
            z[i] = zi
            rz += ri.dot(zi)
        return rz
