"""Backward Euler with a matrix-free linear solve (method.md).

One step solves

    A v_new = M v + dt (f_elastic(x) + f_external),   A = (1 + dt alpha) M + (dt beta + dt^2) K(R)
    x_new   = x + dt v_new

with K(R) = sum_e R Ke R^T never assembled: `stiffness_product` applies it tet by
tet, and per-vertex sums gather over the model's adjacency (no atomics, so the
result is the same bit for bit on every run). PCG (Jacobi-preconditioned CG) is
the default; weighted Jacobi iteration is the cheap alternative.

Effects a scene leaves off are not compiled: gravity, pins and ground contact are
`ti.static` branches fixed when the solver is made, and rotations are only
extracted when some body is corotational. Linear and corotational tets share every
kernel: corotation only changes the per-tet matrix `rotated_Bm` once per step.
"""

import taichi as ti

from fem.elastic import (corner_forces, edge_matrix, is_finite, linear_stress, polar_rotation,
                         quaternion_matrix, refine_rotation, stiffness_block)
from fem.runtime import serial_loops


@ti.data_oriented
class ImplicitSolver:
    """Work fields and kernels of the implicit step for one model."""

    def __init__(self, model, effects):
        n, m = model.n_vertices, model.n_tets
        self.model = model
        self.has_gravity = effects.gravity is not None    # compile-time switch
        self.gravity = effects.gravity or (0.0, 0.0, 0.0)  # m/s^2
        self.has_ground = effects.ground is not None      # compile-time switch
        self.ground = effects.ground or 0.0               # plane height y, m
        self.friction = effects.friction
        self.pins = model.has_pins                        # compile-time: filter pinned rows
        self.serial_tets = serial_loops(m, "tets")        # compile-time: small loops on one thread
        self.serial_vertices = serial_loops(n, "vertices")
        vec = lambda size: ti.Vector.field(3, float, size)   # noqa: E731
        self.rotations = ti.Matrix.field(3, 3, float, m)  # R per tet (identity for linear tets)
        self.rotated_Bm = ti.Matrix.field(3, 3, float, m) # Bm R^T: the only form the solve needs
        self.quaternions = ti.Vector.field(4, float, m)   # the same R as (x, y, z, w): next step's warm start
        self.corner = vec(4 * m)                          # per-corner values before the gather
        self.b, self.r, self.z, self.p, self.Ap = vec(n), vec(n), vec(n), vec(n), vec(n)
        self.solution = vec(n)                            # v_new while solving
        self.block_inverse = ti.Matrix.field(3, 3, float, n)  # Jacobi preconditioner, inverse 3x3 blocks of A
        self.x_backup, self.v_backup = vec(n), vec(n)
        self.contact = ti.field(ti.i32, n if self.has_ground else 1)   # 1: on the ground this step
        self.pressed = ti.field(ti.i32, n if self.has_ground else 1)   # 1: the ground pushed it last step
        self.rz = ti.field(float, ())                     # PCG scalars stay on the device
        self.rr = ti.field(float, ())
        self.beta = ti.field(float, ())
        self.iterations = ti.field(ti.i32, ())
        self.active = ti.field(ti.i32, ())                # 1 while PCG iterates
        self.reset_rotations()

    # ------------------------------------------------------------ per-tet kernels

    @ti.kernel
    def reset_rotations(self):
        """Every tet unrotated: R = I and rotated_Bm = Bm (what linear tets always use)."""
        ti.loop_config(serialize=self.serial_tets)
        for e in self.rotations:
            self.rotations[e] = ti.Matrix.identity(float, 3)
            self.quaternions[e] = ti.Vector([0.0, 0.0, 0.0, 1.0])
            self.rotated_Bm[e] = self.model.Bm[e]

    @ti.func
    def edges(self, x: ti.template(), e):
        """Ds of tet e for the vertex values x (positions or velocities)."""
        t = self.model.tets[e]
        return edge_matrix(x[t[0]], x[t[1]], x[t[2]], x[t[3]])

    @ti.kernel
    def extract_rotations(self, x: ti.template(), svd: ti.template()):
        """R = polar rotation of F for every corotational tet, and rotated_Bm = Bm R^T.

        svd=False: warm-started iterative extraction for tets with det F > 0, and
        the SVD only for inverted or flat tets, where its reflection-safe answer
        matters; svd=True: the SVD for every tet (the reference).
        """
        ti.loop_config(serialize=self.serial_tets)
        for e in self.rotations:
            R = ti.Matrix.identity(float, 3)
            if self.model.corotational[e]:
                F = self.edges(x, e) @ self.model.Bm[e]
                if ti.static(not svd):
                    if F.determinant() > 0:
                        q = refine_rotation(F, self.quaternions[e], 8)
                        self.quaternions[e] = q
                        R = quaternion_matrix(q)
                    else:
                        R = polar_rotation(F)
                else:
                    R = polar_rotation(F)
            self.rotations[e] = R
            self.rotated_Bm[e] = self.model.Bm[e] @ R.transpose()

    # Corotational FEM without a rotation in the inner loop: sigma is isotropic, so
    #     R sigma(sym(R^T F) - I) Bm^T = sigma(sym(Ds Bm R^T) - I) (Bm R^T)^T,
    # i.e. f = -R Ke (R^T x - X) is the linear formula with Bm replaced by Bm R^T
    # (rotated_Bm, refreshed once per step). Linear tets keep rotated_Bm = Bm.

    @ti.kernel
    def elastic_forces(self, x: ti.template()):
        """corner <- f_e = -R Ke (R^T x_e - X_e) per tet (linear: R = I)."""
        ti.loop_config(serialize=self.serial_tets)
        for e in self.rotations:
            F = self.edges(x, e) @ self.rotated_Bm[e]               # F R^T
            eps = 0.5 * (F + F.transpose()) - ti.Matrix.identity(float, 3)
            self.store_corners(e, linear_stress(eps, self.model.mu[e], self.model.lam[e]))

    @ti.kernel
    def stiffness_product(self, u: ti.template(), w: ti.template()):
        """corner <- (K(R) d)_e per tet for the direction d = u + beta w (N/m times m/s)."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.n_tets):
            self.tet_stiffness(e, u, w)

    @ti.func
    def tet_stiffness(self, e, u: ti.template(), w: ti.template()):
        """One tet's share of K(R) d, d = u + beta w: taking d = z + beta p here fuses
        the CG direction update into this pass."""
        beta = self.beta[None]
        t = self.model.tets[e]
        d0, d1 = u[t[0]] + beta * w[t[0]], u[t[1]] + beta * w[t[1]]
        d2, d3 = u[t[2]] + beta * w[t[2]], u[t[3]] + beta * w[t[3]]
        dF = edge_matrix(d0, d1, d2, d3) @ self.rotated_Bm[e]
        eps = 0.5 * (dF + dF.transpose())
        self.store_corners(e, -linear_stress(eps, self.model.mu[e], self.model.lam[e]))

    @ti.func
    def store_corners(self, e, P):
        f0, f1, f2, f3 = corner_forces(P, self.rotated_Bm[e], self.model.rest_volume[e])
        self.corner[4 * e + 0] = f0
        self.corner[4 * e + 1] = f1
        self.corner[4 * e + 2] = f2
        self.corner[4 * e + 3] = f3

    # ------------------------------------------------------------ per-vertex kernels

    @ti.func
    def gather(self, i):
        """Sum of the corner values of every tet around vertex i."""
        s = ti.Vector.zero(float, 3)
        for j in range(self.model.adjacency_start[i], self.model.adjacency_start[i + 1]):
            s += self.corner[self.model.adjacency[j]]
        return s

    @ti.func
    def filtered(self, i, a):
        """Zero the constrained rows: pinned vertices, and the normal of those on the ground
        (filtered CG, Baraff & Witkin 1998)."""
        if ti.static(self.pins):
            a *= self.model.free[i]
        if ti.static(self.has_ground):
            if self.contact[i]:
                a[1] = 0.0
        return a

    @ti.kernel
    def build_preconditioner(self, cM: float, cK: float):
        """block_inverse <- inverse of the 3x3 diagonal blocks of A = cM M + cK K(R)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in self.block_inverse:
            # a pinned vertex keeps an identity block, so the inverse exists even where mass is 0
            block = (cM * self.model.mass[i] + 1.0 - self.model.free[i]) * ti.Matrix.identity(float, 3)
            for j in range(self.model.adjacency_start[i], self.model.adjacency_start[i + 1]):
                slot = self.model.adjacency[j]
                e, k = slot // 4, slot % 4
                B = self.rotated_Bm[e]
                h = -(B[0, :] + B[1, :] + B[2, :])       # rotated shape gradient of corner k
                if k < 3:
                    h = B[k, :]
                block += cK * stiffness_block(h, self.model.rest_volume[e], self.model.mu[e], self.model.lam[e])
            self.block_inverse[i] = block.inverse()

    @ti.kernel
    def assemble_rhs(self, x: ti.template(), v: ti.template(), dt: float) -> float:
        """b <- M v + dt (f_elastic + M g); solution <- v (warm start).

        Returns the squared scale the residual is measured against: the sum of the
        squared sizes of b's three terms. Not |b|^2 itself: for a body resting under
        gravity the elastic force cancels gravity and |b| -> 0, which would ask the
        solve for ever more digits of nothing.
        """
        scale = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in self.b:
            m = self.model.mass[i]
            f = self.gather(i)
            g = ti.Vector.zero(float, 3)
            if ti.static(self.has_gravity):
                g = m * ti.Vector(self.gravity, dt=float)
            self.b[i] = m * v[i] + dt * (f + g)    # kept whole: the ground's reaction is read from it
            self.solution[i] = self.filtered(i, v[i])
            if ti.static(self.has_ground):
                if self.contact[i]:   # prescribed: land exactly on the plane this step
                    self.solution[i][1] = (self.ground - x[i][1]) / dt
            self.p[i] = ti.Vector.zero(float, 3)
            scale += (self.filtered(i, m * v[i]).norm_sqr() + dt * dt * self.filtered(i, f).norm_sqr()
                      + dt * dt * self.filtered(i, g).norm_sqr())
        self.beta[None] = 0.0
        return scale

    @ti.kernel
    def start_residual(self, cM: float, cK: float) -> float:
        """r <- b - A solution, z <- P r, rz <- r.z. Returns |r|^2."""
        rz, rr = 0.0, 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in self.r:
            Ax = cM * self.model.mass[i] * self.solution[i] + cK * self.gather(i)
            r = self.filtered(i, self.b[i] - Ax)
            z = self.filtered(i, self.block_inverse[i] @ r)
            self.r[i], self.z[i] = r, z
            rz += r.dot(z)
            rr += r.dot(r)
        self.rz[None] = rz
        self.rr[None] = rr
        self.iterations[None] = 0
        self.active[None] = 1
        return rr

    @ti.kernel
    def cg_iterations(self, cM: float, cK: float, target: float, cap: ti.i32, unroll: ti.template()) -> float:
        """Up to `unroll` PCG iterations in one launch; returns |r|^2 after the last one done.

        Each iteration is three parallel passes (tets: K d; vertices: p, Ap and p.Ap;
        vertices: x, r, z and r.z, r.r) with the scalar steps between them run
        serially on the device. Once |r|^2 <= target or `cap` iterations are done,
        `active` drops to 0 and the remaining passes loop over nothing, so the
        iteration count is exact while Python launches one kernel per `unroll`.
        """
        n_tets, n = self.model.n_tets, self.model.n_vertices
        for _ in ti.static(range(unroll)):
            on = self.active[None]
            ti.loop_config(serialize=self.serial_tets)
            for e in range(n_tets * on):
                self.tet_stiffness(e, self.z, self.p)
            pAp = 0.0
            beta = self.beta[None]
            ti.loop_config(serialize=self.serial_vertices)
            for i in range(n * on):
                p = self.z[i] + beta * self.p[i]
                Ap = self.filtered(i, cM * self.model.mass[i] * p + cK * self.gather(i))
                self.p[i], self.Ap[i] = p, Ap
                pAp += p.dot(Ap)
            alpha = 0.0
            if pAp > 0:
                alpha = self.rz[None] / pAp
            rz, rr = 0.0, 0.0
            ti.loop_config(serialize=self.serial_vertices)
            for i in range(n * on):
                self.solution[i] += alpha * self.p[i]
                r = self.r[i] - alpha * self.Ap[i]
                z = self.filtered(i, self.block_inverse[i] @ r)
                self.r[i], self.z[i] = r, z
                rz += r.dot(z)
                rr += r.dot(r)
            if on:
                self.beta[None] = 0.0
                if self.rz[None] > 0:
                    self.beta[None] = rz / self.rz[None]
                self.rz[None] = rz
                self.rr[None] = rr
                self.iterations[None] += 1
                if not (rr > target and self.iterations[None] < cap):
                    self.active[None] = 0
        return self.rr[None]

    @ti.kernel
    def jacobi_update(self, cM: float, cK: float, omega: float) -> float:
        """solution += omega P (b - A solution). Returns |b - A solution|^2 before the update."""
        rr = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in self.r:
            Ax = cM * self.model.mass[i] * self.solution[i] + cK * self.gather(i)
            r = self.filtered(i, self.b[i] - Ax)
            self.solution[i] += omega * self.filtered(i, self.block_inverse[i] @ r)
            rr += r.dot(r)
        return rr

    @ti.kernel
    def commit(self, x: ti.template(), v: ti.template(), dt: float) -> ti.i32:
        """v <- solution, x <- x + dt v; keeps a backup. Returns the count of non-finite vertices."""
        bad = 0
        ti.loop_config(serialize=self.serial_vertices)
        for i in x:
            self.x_backup[i], self.v_backup[i] = x[i], v[i]
            v[i] = self.solution[i]
            x[i] += dt * self.solution[i]
            if not is_finite(x[i].sum() + v[i].sum()):
                bad += 1
        return bad

    @ti.kernel
    def restore(self, x: ti.template(), v: ti.template()):
        ti.loop_config(serialize=self.serial_vertices)
        for i in x:
            x[i], v[i] = self.x_backup[i], self.v_backup[i]

    @ti.kernel
    def detect_contacts(self, x: ti.template(), v: ti.template(), dt: float):
        """Active set of the ground constraint: a free vertex is in contact when its velocity
        would take it below the plane this step, or when the plane still pushed it last step.
        The solve then fixes its normal velocity so that it lands on the plane."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in x:
            self.contact[i] = 0
            if self.model.free[i] > 0 and (x[i][1] + dt * v[i][1] < self.ground or self.pressed[i]):
                self.contact[i] = 1

    @ti.kernel
    def ground_reaction(self, cM: float, cK: float):
        """pressed <- contact vertices the plane pushes up: (A v - b)_y > 0 (after
        stiffness_product(solution)); the others may lift off next step."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in self.pressed:
            self.pressed[i] = 0
            if self.contact[i]:
                Av = cM * self.model.mass[i] * self.solution[i] + cK * self.gather(i)
                if Av[1] - self.b[i][1] > 0:
                    self.pressed[i] = 1

    @ti.kernel
    def ground_contact(self, x: ti.template(), v: ti.template()):
        """Friction on the vertices in contact (removes part of the tangential velocity),
        and no vertex left below the plane."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in x:
            if x[i][1] < self.ground:
                self.pressed[i] = 1      # caught below the plane: in contact next step
            if self.contact[i] or x[i][1] < self.ground:
                x[i][1] = ti.max(x[i][1], self.ground)
                v[i][1] = ti.max(v[i][1], 0.0)
                v[i][0] *= 1.0 - self.friction
                v[i][2] *= 1.0 - self.friction

    @ti.kernel
    def matrix_product(self, u: ti.template(), out: ti.template(), cM: float, cK: float):
        """out <- A u, gathered from `corner` after stiffness_product(u): for tests and checks."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in out:
            out[i] = self.filtered(i, cM * self.model.mass[i] * u[i] + cK * self.gather(i))
