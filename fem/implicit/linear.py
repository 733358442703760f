"""The linear solve of a Newton iteration, H d = -grad E, matrix-free (method.md, section 7).

H = cM M + cK K(R) is never assembled: the stiffness product runs tet by tet into corner
values (fem/implicit/elasticity.py) and each vertex gathers its own, filtered by the
constraints. Two solvers:

- PCG, preconditioned by fem/implicit/preconditioner.py. CG_UNROLL iterations run in one
  kernel launch (up to SERIAL_UNROLL where every loop runs on one thread, a small mesh),
  with the scalar steps on the device and the direction update fused into
  the stiffness pass; the iterates are those of textbook PCG.
- Weighted block-Jacobi iteration, d += omega D^-1 (rhs - H d), omega from H's spectrum
  (up to SERIAL_UNROLL iterations a launch on a small mesh).

Both stop once the weighted residual sum_b w_b |r_b|^2 (w_b: IncrementalPotential.body_weight)
reaches the target, or at the iteration cap. On a small mesh whose bodies nothing couples (no
contact between them; two bodies or more), each body runs PCG of its own (`body_iteration`): H is then block
diagonal by body, and PCG's scalars shared over the blocks make one polynomial serve every
body's spectrum at once, a stiff body's holding back a soft one's (the ground drops of
tests/test_energy.py: 400 iterations a solve, the cap, where the stiffest body alone took 37).
Each body stops at the target on its own weighted residual, as Newton's test is each body's own.

Fields (n vertices of the capacity):
    solution (n, 3)      d, m/s: the first guess in, the direction out
    r, z, p, Ap (n, 3)   PCG's residual, preconditioned residual, direction and H p
    rz, rr, cg_beta ()   PCG's scalars r.z, weighted r.r and beta, kept on the device
    iterations ()        PCG iterations of this solve
    active ()            1 while PCG iterates
    body_rz, body_rr, body_pAp, body_next, body_beta (bodies,)
                         each body's own PCG scalars (r.z, weighted r.r, p.Ap, the next r.z, beta)
    body_active (bodies,)  1 while that body's PCG iterates
"""

import numpy as np
import taichi as ti

from fem import runtime

CG_UNROLL = 2            # PCG iterations per kernel launch: fewer launches, same iterates
SERIAL_UNROLL = 32       # at most this many where the launch runs them in a loop of its own (`cg_iterations`)
TWO_I32 = ti.types.vector(2, ti.i32)
TWO_F64 = ti.types.vector(2, ti.f64)


@ti.data_oriented
class LinearSolver:
    """PCG and Jacobi iteration on H for one model: H u from `potential` (apply_H) and
    `elasticity` (the stiffness product), right-hand side `potential.rhs`, preconditioner
    `preconditioning`, constraints from `effects`, sleeping bodies' tets skipped (`sleep`)."""

    def __init__(self, model, potential, elasticity, preconditioning, effects, sleep, switches):
        n = model.capacity.vertices
        self.model, self.potential, self.elasticity = model, potential, elasticity
        self.preconditioning, self.effects, self.sleep = preconditioning, effects, sleep
        self.serial_tets, self.serial_vertices = switches.serial_tets, switches.serial_vertices
        self.capacity_loops = runtime.capacity_loops()        # loops over the capacity (a GPU's grid fits it)
        vec = lambda size: ti.Vector.field(3, float, size)   # noqa: E731
        self.solution = vec(n)
        self.r, self.z, self.p, self.Ap = vec(n), vec(n), vec(n), vec(n)
        self.rz = ti.field(float, ())
        self.rr = ti.field(float, ())
        self.capped = False           # the last solve stopped at max_iterations, unconverged
        self.cg_beta = ti.field(float, ())
        self.iterations = ti.field(ti.i32, ())
        self.active = ti.field(ti.i32, ())
        # every loop on one thread and no pairs coupling bodies: each body its own PCG (`body_iteration`)
        self.separate = (switches.serial_tets and switches.serial_vertices and not switches.contact
                         and not self.capacity_loops)
        nb = model.capacity.bodies if self.separate else 1
        self.body_rz, self.body_rr, self.body_pAp = ti.field(float, nb), ti.field(float, nb), ti.field(float, nb)
        self.body_next, self.body_beta = ti.field(float, nb), ti.field(float, nb)
        self.body_active = ti.field(ti.i32, nb)

    def load(self):
        self.omega_key, self.omega = None, None               # Jacobi iteration's weight, and its (cM, cK)

    def forget_weight(self):
        """The materials or dt changed: the next Jacobi iteration finds its weight again."""
        self.omega_key = None

    def solve(self, cM, cK, target, max_iterations, preconditioner, start, warm, rebuild=False, forcing=0.0):
        """H d = rhs from the first guess `start.first_direction(warm)` writes into `solution`, until the
        weighted residual sum_b |r_b|^2 w_b <= target; returns the iterations. preconditioner: "jacobi" or
        "two-level" (PCG), None (Jacobi iteration). rebuild: the blocks of the preconditioner are built
        first, at the rotations now. Both in the solve's first launch (`begin`): two launches fewer a
        Newton iteration. `capped` <- it stopped at max_iterations unconverged.
        forcing: inexact Newton's factor (Newton.solve's target is max(1, forcing rho), rho its
        largest body's); where each body runs its own PCG, each stops at max(1, forcing rho_b), its own
        (IncrementalPotential.body_ratio): a stalled body's rho let every other body stop at once."""
        if preconditioner is not None:
            two_level = preconditioner == "two-level"
            apart = self.separate and len(self.model.bodies) > 1 and not two_level   # one body: PCG as it was
            active, iterations = self.start_residual(cM, cK, target, forcing, two_level, apart, start, warm,
                                                     rebuild) > target, 0
            while active:
                active, iterations = self.cg_iterations(cM, cK, target, forcing, max_iterations, CG_UNROLL,
                                                        two_level, apart)
        else:
            self.start_jacobi(cM, cK, start, warm, rebuild)
            iterations, rr = 0, float("inf")
            while iterations < max_iterations and not rr <= target:
                if self.serial_tets and self.serial_vertices:     # a small mesh: many iterations a launch
                    done, rr = self.jacobi_iterations(cM, cK, self.omega, target,
                                                      min(SERIAL_UNROLL, max_iterations - iterations))
                    iterations += int(done)
                else:
                    self.elasticity.stiffness_product(self.solution)
                    rr = self.jacobi_update(cM, cK, self.omega)
                    iterations += 1
            self.rr[None] = rr
        self.capped = iterations >= max_iterations and self.rr[None] > target
        return int(iterations)

    @ti.func
    def begin(self, cM, cK, start: ti.template(), warm, rebuild: ti.template()):
        """The blocks built (rebuild), then the first guess d in `solution` (`solve`)."""
        if ti.static(rebuild):
            self.preconditioning.build_blocks(cM, cK)
        start.first_direction(warm)

    @ti.kernel
    def start_jacobi(self, cM: float, cK: float, start: ti.template(), warm: ti.i32, rebuild: ti.template()):
        self.begin(cM, cK, start, warm, rebuild)

    @ti.kernel
    def start_residual(self, cM: float, cK: float, target: float, forcing: ti.f64, two_level: ti.template(),
                       apart: ti.template(), start: ti.template(), warm: ti.i32, rebuild: ti.template()) -> float:
        """`begin`, then r <- filtered(rhs) - H d, z <- P r, rz <- r.z, for the first guess d.
        Returns the weighted residual sum_i w_b(i) |r_i|^2 (each body its own PCG: the largest
        body's, and those above the target iterate)."""
        self.begin(cM, cK, start, warm, rebuild)
        if ti.static(apart):
            self.start_bodies()
        self.elasticity.stiffness_pass(self.solution)         # K d, into the corners
        if ti.static(self.effects.has_contact):
            self.effects.contact.product_pass(self.solution, self.solution, 0.0, 1)
        rz, rr = 0.0, 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            r = self.effects.filtered(i, self.potential.rhs[i]) - self.potential.apply_H(i, self.solution, cM, cK)
            self.r[i] = r
            self.p[i] = ti.Vector.zero(float, 3)
            if ti.static(not two_level):
                z = self.effects.filtered(i, self.preconditioning.jacobi(i, r))
                self.z[i] = z
                rz += r.dot(z)
                if ti.static(apart):
                    self.add_to_body(i, r, z)
            rr += self.potential.body_weight[self.model.vertex_body[i]] * r.dot(r)
        if ti.static(two_level):
            rz = self.preconditioning.two_level_precondition(self.r, self.z, 1)
        self.rz[None] = rz
        self.rr[None] = rr
        self.cg_beta[None] = 0.0
        self.iterations[None] = 0
        self.active[None] = 1
        if ti.static(apart):
            rr = self.end_bodies(target, forcing, 1)
        return rr

    @ti.kernel
    def cg_iterations(self, cM: float, cK: float, target: float, forcing: ti.f64, cap: ti.i32, unroll: ti.template(),
                      two_level: ti.template(), apart: ti.template()) -> TWO_I32:
        """Up to `unroll` PCG iterations in one launch (SERIAL_UNROLL where every loop runs on one thread).

        Each iteration is three passes (tets: K d; vertices: p, Ap and p.Ap; vertices: d, r, z
        and r.z, weighted r.r; two-level: z and r.z in three more, `Preconditioner.two_level_precondition`)
        with the scalar steps between them. Parallel passes are top-level loops, so the launch
        repeats them `unroll` times in its code; once the weighted |r|^2 <= target or `cap`
        iterations are done, `active` drops to 0 and the remaining passes loop over nothing, so
        the iteration count is exact. Where every loop runs on one thread (a small mesh, block
        Jacobi) the iterations are a loop of the launch itself, which stops when PCG does: a
        launch costs more than an iteration there (the ground drops of tests/test_energy.py: 270
        vertices, then 400 iterations a solve). Returns (`active`, the iterations so far).
        """
        if ti.static(apart):
            ti.loop_config(serialize=True)
            for _ in range(SERIAL_UNROLL):
                if not self.active[None]:
                    break
                self.body_iteration(cM, cK, target, forcing, cap)
        elif ti.static(self.serial_tets and self.serial_vertices and not two_level and not self.capacity_loops):
            ti.loop_config(serialize=True)
            for _ in range(SERIAL_UNROLL):
                if not self.active[None]:
                    break
                self.cg_iteration(cM, cK, target, cap, two_level)
        else:
            for _ in ti.static(range(unroll)):
                self.cg_iteration(cM, cK, target, cap, two_level)
        return ti.Vector([self.active[None], self.iterations[None]], ti.i32)

    @ti.func
    def cg_iteration(self, cM, cK, target, cap, two_level: ti.template()):
        """One PCG iteration (none once `active` is 0): `cg_iterations`."""
        n_tets, n = self.model.tet_count[None], self.model.vertex_count[None]
        fixed = ti.static(self.capacity_loops)
        all_tets, all_vertices = ti.static(self.model.capacity.tets, self.model.capacity.vertices)
        on = self.active[None]
        beta = self.cg_beta[None]
        tets, vertices = n_tets * on, n * on
        ti.loop_config(serialize=self.serial_tets)
        for e in range(all_tets if fixed else tets):
            if e < tets and self.sleep.tet_awake(e):
                self.elasticity.tet_stiffness(e, self.z, self.p, beta)
        if ti.static(self.effects.has_contact):
            self.effects.contact.product_pass(self.z, self.p, beta, on)
        pAp = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(all_vertices if fixed else vertices):
            if i >= vertices:
                continue
            p = self.z[i] + beta * self.p[i]
            self.p[i] = p
            Ap = self.potential.apply_H(i, self.p, cM, cK)
            self.Ap[i] = Ap
            pAp += p.dot(Ap)
        step = 0.0
        if pAp > 0:
            step = self.rz[None] / pAp
        rz, rr = 0.0, 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(all_vertices if fixed else vertices):
            if i >= vertices:
                continue
            self.solution[i] += step * self.p[i]
            r = self.r[i] - step * self.Ap[i]
            self.r[i] = r
            if ti.static(not two_level):              # block Jacobi: z in the same pass
                z = self.effects.filtered(i, self.preconditioning.jacobi(i, r))
                self.z[i] = z
                rz += r.dot(z)
            rr += self.potential.body_weight[self.model.vertex_body[i]] * r.dot(r)
        if ti.static(two_level):
            rz = self.preconditioning.two_level_precondition(self.r, self.z, on)
        if on:
            self.cg_beta[None] = 0.0
            if self.rz[None] > 0:
                self.cg_beta[None] = rz / self.rz[None]
            self.rz[None] = rz
            self.rr[None] = rr
            self.iterations[None] += 1
            if not (rr > target and self.iterations[None] < cap):
                self.active[None] = 0

    # ------------------------------------------------------------ each body its own PCG (a small mesh, no pairs)

    @ti.func
    def start_bodies(self):
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_next[b], self.body_rr[b], self.body_beta[b] = 0.0, 0.0, 0.0

    @ti.func
    def add_to_body(self, i, r, z):
        """Vertex i's share of its body's next r.z and weighted r.r."""
        b = self.model.vertex_body[i]
        self.body_next[b] += r.dot(z)
        self.body_rr[b] += self.potential.body_weight[b] * r.dot(r)

    @ti.func
    def end_bodies(self, target, forcing, cap):
        """After a pass of `add_to_body`: each iterating body's beta and r.z; a body at its own target
        stops (`solve`: forcing). Returns the largest body's weighted r.r; `active` <- some body iterates."""
        largest, iterating = 0.0, 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.iterations[None] == 0 or self.body_active[b]:
                self.body_beta[b] = 0.0
                if self.body_rz[b] > 0 and self.iterations[None] > 0:
                    self.body_beta[b] = self.body_next[b] / self.body_rz[b]
                self.body_rz[b] = self.body_next[b]
                own = target
                if forcing > 0:
                    own = ti.min(target, ti.max(1.0, forcing * self.potential.body_ratio[b]))
                self.body_active[b] = int(self.body_rr[b] > own)
            largest = ti.max(largest, self.body_rr[b])
            iterating += self.body_active[b]
        self.rr[None] = largest
        self.active[None] = int(iterating > 0 and self.iterations[None] < cap)
        return largest

    @ti.func
    def body_iteration(self, cM, cK, target, forcing, cap):
        """One PCG iteration of every body still iterating, as `cg_iteration` but each with its own
        scalars: H p for p = z + beta_b p, the step rz_b / p.Ap_b, then r, z and the body's sums
        (`add_to_body`, `end_bodies`). A body that has stopped keeps its d and r."""
        on = ti.static(self.body_active)
        for b in range(self.model.body_count[None]):
            if on[b]:
                self.body_pAp[b], self.body_next[b], self.body_rr[b] = 0.0, 0.0, 0.0
        for e in range(self.model.tet_count[None]):
            b = self.model.tet_body[e]
            if on[b] and self.sleep.tet_awake(e):
                self.elasticity.tet_stiffness(e, self.z, self.p, self.body_beta[b])
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if on[b]:
                p = self.z[i] + self.body_beta[b] * self.p[i]
                self.p[i] = p
                Ap = self.potential.apply_H(i, self.p, cM, cK)
                self.Ap[i] = Ap
                self.body_pAp[b] += p.dot(Ap)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if on[b]:
                step = 0.0
                if self.body_pAp[b] > 0:
                    step = self.body_rz[b] / self.body_pAp[b]
                self.solution[i] += step * self.p[i]
                r = self.r[i] - step * self.Ap[i]
                self.r[i] = r
                z = self.effects.filtered(i, self.preconditioning.jacobi(i, r))
                self.z[i] = z
                self.add_to_body(i, r, z)
        self.iterations[None] += 1
        self.end_bodies(target, forcing, cap)

    @ti.kernel
    def jacobi_update(self, cM: float, cK: float, omega: float) -> float:
        """d += omega P (rhs - H d) (after stiffness_product(d)). Returns the weighted
        |rhs - H d|^2 before the update."""
        return self.jacobi_pass(cM, cK, omega)

    @ti.kernel
    def jacobi_iterations(self, cM: float, cK: float, omega: float, target: ti.f64, most: ti.i32) -> TWO_F64:
        """Up to `most` Jacobi iterations in one launch, each `stiffness_pass` then `jacobi_pass`,
        on one thread (a small mesh); stops after the first whose residual before it is <= target.
        Returns (iterations, that residual)."""
        done, rr = 0, ti.cast(0.0, ti.f64)
        ti.loop_config(serialize=True)
        for _ in range(most):
            self.elasticity.stiffness_pass(self.solution)
            rr = ti.cast(self.jacobi_pass(cM, cK, omega), ti.f64)
            done += 1
            if rr <= target:
                break
        return ti.Vector([done, rr], ti.f64)

    @ti.func
    def jacobi_pass(self, cM, cK, omega):
        """`jacobi_update`, inside another kernel."""
        rr = 0.0
        if ti.static(self.effects.has_contact):
            self.effects.contact.product_pass(self.solution, self.solution, 0.0, 1)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            r = self.effects.filtered(i, self.potential.rhs[i]) - self.potential.apply_H(i, self.solution, cM, cK)
            self.solution[i] += omega * self.effects.filtered(i, self.preconditioning.jacobi(i, r))
            rr += self.potential.body_weight[self.model.vertex_body[i]] * r.dot(r)
        return rr

    def jacobi_weight(self, cM, cK, omega=None):
        """omega = 1.5 / lambda_max(P H), lambda_max from 30 power iterations (rotations ignored:
        they barely move the spectrum), so the iteration cannot diverge (needs omega < 2 / lambda_max).
        omega: a weight the settings fix instead."""
        if omega:
            self.omega = omega
            return
        key = (cM, cK)
        if key != self.omega_key:
            P = self.preconditioning.exact_blocks(cM, cK)
            u = np.random.default_rng(0).standard_normal((self.model.n_vertices, 3))
            lam = 1.0
            for _ in range(30):
                u /= np.linalg.norm(u)
                w = np.einsum("nij,nj->ni", P, self.apply_matrix(u, cM, cK))
                lam = float(np.vdot(u, w)) if np.vdot(u, u) > 0 else 1.0
                u = w
            self.omega, self.omega_key = 1.5 / max(lam, 1e-12), key

    # ------------------------------------------------------------ for checks and tests

    def apply_matrix(self, u, cM, cK):
        """H u for a (n, 3) numpy array u with the current rotations."""
        self.model.write(self.p, u)
        self.elasticity.stiffness_product(self.p)
        self.matrix_product(self.p, self.Ap, cM, cK)
        return self.Ap.to_numpy()[:self.model.n_vertices].astype(np.float64)

    @ti.kernel
    def matrix_product(self, u: ti.template(), out: ti.template(), cM: float, cK: float):
        """out <- H u, gathered from the corners after stiffness_product(u)."""
        if ti.static(self.effects.has_contact):
            self.effects.contact.product_pass(u, u, 0.0, 1)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            out[i] = self.potential.apply_H(i, u, cM, cK)

    def apply_preconditioner(self, r, preconditioner):
        """P r for a (n, 3) numpy array r, with the preconditioner ("jacobi" or "two-level") of the last step."""
        self.model.write(self.r, r)
        self.preconditioner_product(preconditioner == "two-level")
        return self.z.to_numpy()[:self.model.n_vertices].astype(np.float64)

    @ti.kernel
    def preconditioner_product(self, two_level: ti.template()):
        if ti.static(two_level):
            self.preconditioning.two_level_precondition(self.r, self.z, 1)
        else:
            for i in range(self.model.vertex_count[None]):
                self.z[i] = self.effects.filtered(i, self.preconditioning.jacobi(i, self.r[i]))
