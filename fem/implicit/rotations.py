"""The tets' rotations R, extracted at the step's iterates (fem/rotation.py has the maths).

Corotational FEM without a rotation in the inner loop: sigma is isotropic, so

    R sigma(sym(R^T F) - I) Bm^T = sigma(sym(Ds Bm R^T) - I) (Bm R^T)^T,

i.e. f = -R Ke (R^T x - X) is the linear formula with Bm replaced by Bm R^T (`rotated_Bm`).
Linear tets keep rotated_Bm = Bm, so linear and corotational tets share every kernel.

Fields (m tets of the capacity):
    rotated_Bm (m, 3x3)     Bm R^T at the current iterate, 1/m
    quaternions (m, 4)      R as (x, y, z, w): the next warm start
    start (m, 4)            R(x_n) as quaternions, kept for backward Euler's damping (`keep_start`)
    turn (m, 3)             (x, y, z) of R_n R_(n-1)^-1, the last step's turn
    twist (m,)              twist stiffness of the Newton matrix, Pa
    needs_svd (m,)          1: the tet's R comes from the SVD
    largest_turn ()         largest |turn|^2 this step: sin^2(angle / 2)
"""

import math
import time

import taichi as ti

from fem.rotation import (conjugate, newton_rotation, polar_rotation, quaternion_matrix, quaternion_of,
                          quaternion_product)


@ti.func
def twist_stiffness(trace_S, mu, lam):
    """lam_t = max(0, (psi_i + psi_j) / (s_i + s_j)) with every s_i = tr S / 3 (Pa), where
    psi_i = 2 mu (s_i - 1) + lam (tr S - 3): the twist curvature of the corotated energy."""
    pair = 2.0 * trace_S / 3.0
    lam_t = 0.0
    if pair > 0:
        lam_t = ti.max(0.0, (2.0 * mu * (pair - 2.0) + 2.0 * lam * (trace_S - 3.0)) / pair)
    return lam_t


# The Newton matrix R Ke R^T misses the curvature of Psi when a tet turns: the "twist"
# modes (skew parts of R^T dF) get none, where the exact Hessian of the corotated energy
# gives (psi_i + psi_j) / (s_i + s_j) for singular values s_i, s_j (Smith et al. 2019,
# "Analytic eigensystems for isotropic distortion energies"): positive in a stretched
# tet, and for a near-incompressible one far larger than mu. Without it Newton overshoots
# and the line search halves every step; `twist` adds it, projected to >= 0 and with all
# s_i taken equal to their mean (tr S / 3), as lam_t |skew(R^T dF)|^2.


@ti.data_oriented
class Rotations:
    """Rotation extraction for one model: Newton steps warm-started from the last rotations,
    the SVD where they cannot certify their answer. `sleep`: a sleeping body keeps its rotations."""

    def __init__(self, model, sleep, switches):
        m = model.capacity.tets
        self.model, self.sleep = model, sleep
        self.serial_tets = switches.serial_tets
        self.rotated_Bm = ti.Matrix.field(3, 3, float, m)
        self.quaternions = ti.Vector.field(4, float, m)
        self.turn = ti.Vector.field(3, float, m)
        self.twist = ti.field(float, m)
        self.needs_svd = ti.field(ti.i8, m)
        self.largest_turn = ti.field(float, ())
        self.start = ti.Vector.field(4, float, m) if switches.stiffness_damping else None   # `keep_start`
        self.rotated = False                                  # some tet's R is not I

    def update(self, x, svd, twist, first=False, scale=0.0):
        """Rotations at positions x; returns (ms spent, rad: the largest turn of a tet since the
        last step, inf where some tet needed the SVD; 0 unless first).
        svd: every tet from the SVD (the reference). twist: set the twist stiffness (Newton).
        first: at x_n, the step's first; its Newton steps start from the last step's turn,
        times `scale` (the ratio of the dts; 0: no last step)."""
        start = time.perf_counter()
        left = self.extract_rotations(x, svd, int(twist), int(first), scale)
        if left > 0:
            self.svd_rotations(x, int(twist))
        turned = 0.0
        if first:                                             # how far the blocks' rotations are off, at most
            turned = math.inf if left > 0 else 2.0 * math.asin(math.sqrt(min(float(self.largest_turn[None]), 1.0)))
        self.rotated = True
        ti.sync()
        return 1e3 * (time.perf_counter() - start), turned

    def keep_start(self):
        """start <- the rotations now (R(x_n) at a step's start): backward Euler's damping
        measures each tet's strain rate against them (IncrementalPotential.strain_rate)."""
        self.start.copy_from(self.quaternions)

    def unrotate(self):
        """Every tet back to R = I (after every body switched to linear, or to forget them)."""
        self.reset_rotations()
        self.rotated = False

    @ti.kernel
    def reset_rotations(self):
        """Every tet unrotated: R = I and rotated_Bm = Bm (what linear tets always use)."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.quaternions[e] = ti.Vector([0.0, 0.0, 0.0, 1.0])
            self.turn[e] = ti.Vector.zero(float, 3)
            self.rotated_Bm[e] = self.model.Bm[e]
            self.twist[e] = 0.0

    @ti.kernel
    def extract_rotations(self, x: ti.template(), svd: ti.template(), newton: ti.i32, first: ti.i32,
                          scale: float) -> ti.i32:
        """R = polar rotation of F for every corotational tet, kept as rotated_Bm = Bm R^T.

        svd=False: warm-started Newton steps from last time's R; a tet where they do not
        certify their answer (a start far off, an inverted tet) is left for `svd_rotations`.
        first=1 (at x_n): they start from last time's R turned on by the last step's turn
        (times `scale`, the ratio of the dts; 0: no last step) and record this step's turn.
        On a turning body one step then certifies R where the last R alone needs two.
        svd=True: every corotational tet is left for it (the reference).
        newton=1 also sets each tet's twist stiffness; 0 leaves it 0 (the one-solve step).
        Returns how many tets were left. The SVD lives in its own kernel, compiled only when a
        run first needs it: it is most of the compile time.
        """
        left = 0
        self.largest_turn[None] = 0.0
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.needs_svd[e] = 0
            if not self.sleep.tet_awake(e):      # a sleeping body keeps its rotations
                continue
            if self.model.method(e):
                if ti.static(svd):
                    self.needs_svd[e] = 1
                    left += 1
                else:
                    F = self.model.edges(x, e) @ self.model.Bm[e]
                    last = self.quaternions[e]
                    start = last
                    if first:
                        start = quaternion_product(self.turn_quaternion(e, scale), last).normalized()
                    q, converged = newton_rotation(F, start)
                    self.set_rotation(e, F, quaternion_matrix(q), q, newton)
                    if first:
                        turn = quaternion_product(q, conjugate(last))
                        if turn[3] < 0:                  # -p is the same turn: keep w >= 0
                            turn = -turn
                        t = ti.Vector([turn[0], turn[1], turn[2]]) * (scale > 0 and converged)
                        self.turn[e] = t
                        ti.atomic_max(self.largest_turn[None], t.norm_sqr())
                    if not converged:
                        self.needs_svd[e] = 1
                        left += 1
            else:
                self.turn[e] = ti.Vector.zero(float, 3)
                self.twist[e] = 0.0
                self.quaternions[e] = ti.Vector([0.0, 0.0, 0.0, 1.0])
                self.rotated_Bm[e] = self.model.Bm[e]
        return left

    @ti.func
    def turn_quaternion(self, e, scale):
        """The last step's turn of tet e, its angle times `scale`, as a unit quaternion."""
        v = scale * self.turn[e]
        return ti.Vector([v[0], v[1], v[2], ti.sqrt(ti.max(1.0 - v.norm_sqr(), 0.0))])

    @ti.kernel
    def svd_rotations(self, x: ti.template(), newton: ti.i32):
        """The polar rotation from the SVD (`polar_rotation`) for the tets left by extract_rotations."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            if self.needs_svd[e]:
                F = self.model.edges(x, e) @ self.model.Bm[e]
                R = polar_rotation(F)
                self.set_rotation(e, F, R, quaternion_of(R), newton)

    @ti.func
    def set_rotation(self, e, F, R, q, newton):
        self.quaternions[e] = q                               # the next warm start
        self.rotated_Bm[e] = self.model.Bm[e] @ R.transpose()
        twist = 0.0
        if newton:
            twist = twist_stiffness((R.transpose() @ F).trace(), self.model.mu(e), self.model.lam(e))
        self.twist[e] = twist

