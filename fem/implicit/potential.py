"""The incremental potential E(v) that one implicit step minimises (method.md, section 6).

With the iterate x = x^ + h v, one step finds the velocity v that minimises

    E(v) = 1/2 |v - v^|_M^2 + h/2 v^T D v - h v^T M g + Psi(x^ + h v)        (J)

D = alpha M + beta K(R): Rayleigh damping with the stiffness in the frame of the current
iterate's rotations R, so that a rigid turn is no strain rate and is not damped (beta acts on
deformation rates only; alpha M is a drag on all motion). Psi: the elastic energy (corotated
linear or linear per body, fem/implicit/elasticity.py). Its stationarity condition
M (v - v^) + h D v - h M g - h f(x) = 0 is the integrator's update, and E's Hessian (R held) is

    H = cM M + cK K(R),   cM = 1 + h alpha,  cK = h beta + h^2      (`coefficients`).

With a ground, E also has its contact and friction terms (fem/implicit/effects.py): a
penalty C(x) for vertices below the plane and a lagged friction potential, so the line
search that lowers E lowers them too. Their Hessian is a 3x3 block per vertex, added to H.

What an integrator defines is its inertia target (x^, v^) and its effective step h
(fem/implicit/integrators.py): backward Euler x^ = x_n, v^ = v_n, h = dt; BDF2
x^ = (4 x_n - x_(n-1)) / 3, v^ likewise, h = 2 dt / 3. Every pass here takes them as inputs.

Energies are summed per body in float64 whatever the fields' precision: bodies never
interact, so E = sum_b E_b, and each body has its own line search and stopping test.

Fields (n vertices, bodies of the capacity):
    x0, v0 (n, 3)         the inertia target x^ (m) and v^ (m/s): for backward Euler the step's start
    x, v (n, 3)           the iterate x = x^ + h v (m) and v (m/s)
    rhs (n, 3)            -grad E at the accepted iterate (unfiltered), N s
    body_E (bodies,)      E_b at the last iterate evaluated, J
    body_gradient (bodies,)   |grad_b E|^2, (N s)^2
    body_scale (bodies,)  s_b^2 at the last iterate: the size of its terms there, (N s)^2
    body_momentum (bodies,)   |M v^|_b^2, (N s)^2
    body_floor (bodies,)  round-off floor of |grad_b|^2 this step, (N s)^2: body_near_floor times body_far
    body_near_floor (bodies,)  the floor of a body within its own size L of the origin (Model.body_floor)
    body_size_sq (bodies,)    L^2, m^2
    body_far (bodies,)    max(1, D^2 / L^2), D the body's root-mean-square distance from the origin at the
                          step's first iterate: positions carry round-off relative to D, not to L
    body_weight (bodies,) 1 / (tol^2 s_b^2 + floor_b): weights of the residuals' norm
    body_ratio (bodies,)  |grad_b|^2 body_weight: the body's own rho (<= 1: converged)
    relative ()           max_b |grad_b|^2 / s_b^2 at the last iterate: the squared relative
                          residual, with no floor (what StepInfo.residual reports)
    held_Bm (m, 3x3)      with contact and stiffness damping: Bm R^T of the accepted Newton iterate, the
                          damping's frame in the line search that starts there (`holds_frame`), 1/m
    body_shift (bodies,)  E_b in the iterate's own damping frame less E_b in held_Bm's, J
"""

import taichi as ti

from fem.elastic import corner_forces, energy_density, linear_stress
from fem.rotation import quaternion_matrix

ROUNDOFF = 30.0          # per-body floors of the stopping tests, in units of the precision's epsilon
# The gradient's own floor (Model.body_floor), in units of epsilon, by precision. float32: -grad E
# evaluated in float32 at a state also evaluated in float64 differs by 0.03 to 0.45 eps h E L^2 (the
# benchmark's nine elastic scenes and a box at E 1e8, 20 steps in). At 30 the floor was 60 to 600
# times that noise, and Newton stopped at it: float32 trapezoidal steps ended 2.5 times (epcot:
# 2.89e-4 of the scene's size at t = 2 s, float64 1.69e-4) to 3.4 times (fertility: 3.16e-4, float64
# 0.94e-4) as far from the benchmark's reference as float64's. At 10: 1.80e-4 and 1.02e-4, every
# step converged. float64 keeps 30: there the floor is far below any tolerance and decides only
# whether a body at rest is at rest (a box at rest, E 1e6, nu 0.45, took a CG iteration every step
# at 10). (The ground's float32 noise is above any such floor: Newton stops there because its velocity
# settles, and says whether the gradient met the tolerance.)
GRADIENT_ROUNDOFF = {"f32": 10.0, "f64": 30.0}
# A nearly incompressible body's float32 noise is its volume term's, 0.1 to 1.4 eps h (lam + 2 mu) L^2
# (350 to 4,500 eps h E L^2 at nu 0.49995): its floor takes a quarter of lam + 2 mu where that is more
# than E (nu above 0.455; Model.body_floor). With E alone, a 0.5 m cube at E 1e8 spinning at 10 rad/s
# stopped above its floor on 92 to 100 of 100 steps at nu 0.49 to 0.49995 and took 71 to 100 rigid
# steps; now 0 to 36. float64's noise there is far below any tolerance: a floor raised with it only
# stops Newton short of the tighter passes the energy-momentum step asks for (E 1e11: a rigid step).
VOLUME_ROUNDOFF = {"f32": 0.25, "f64": 0.0}


def damping_dominates(bodies, dt, beta):
    """Some body's stiffness damping over a step outweighs its inertia, dt beta (lam + 2 mu) >= rho L^2
    (L its size; bodies: fem.builder's): the hard cases' 1 m cubes at E 1e9 and nu 0.4999 with beta
    0.1 (897 and 11 at dt 0.02 s), not the built-in scenes (the bunny's 0.019 is their largest)."""
    return any(dt * beta * b.material.longitudinal >= b.material.density * b.size ** 2
               for b in bodies)


@ti.data_oriented
class IncrementalPotential:
    """E(v), grad E(v) and H u for one model, over the parts that define them: `elasticity`
    (Psi's tet terms), `rotations` (R at the iterate), `effects` (gravity, damping,
    constraints) and `sleep` (a sleeping body's terms are 0)."""

    def __init__(self, model, elasticity, rotations, effects, sleep, switches):
        n, nb = model.capacity.vertices, model.capacity.bodies
        self.model, self.elasticity, self.rotations = model, elasticity, rotations
        self.effects, self.sleep = effects, sleep
        self.has_gravity = switches.gravity
        self.has_stiffness_damping = switches.stiffness_damping
        self.serial_tets, self.serial_vertices = switches.serial_tets, switches.serial_vertices
        vec = lambda size: ti.Vector.field(3, float, size)   # noqa: E731
        self.x0, self.v0 = vec(n), vec(n)
        self.x, self.v = vec(n), vec(n)
        self.rhs = vec(n)
        self.body_E = ti.field(ti.f64, nb)
        self.body_gradient = ti.field(ti.f64, nb)
        self.body_scale = ti.field(ti.f64, nb)
        self.body_momentum = ti.field(ti.f64, nb)
        self.body_floor = ti.field(ti.f64, nb)
        self.body_near_floor = ti.field(ti.f64, nb)
        self.body_size_sq = ti.field(ti.f64, nb)
        self.body_far = ti.field(ti.f64, nb)
        self.body_weight = ti.field(float, nb)
        self.body_ratio = ti.field(ti.f64, nb)
        self.relative = ti.field(ti.f64, ())
        self.rate_from_start = ti.field(ti.i32, ())       # 1: backward Euler's damping (`turn_rate`)
        # The damping term h/2 v^T beta K(R) v is taken with R at the iterate, but its gradient, h beta K(R) v,
        # holds R: along a line search E had a slope the gradient did not have (the 20-box pile, f64: E's
        # change over a small step 0.05 to -17 times the slope's prediction once the gradient was small, and
        # 1.000 with beta 0; the line search found no descent and stopped the step unconverged). With
        # contact (where those steps were measured), and where some body's damping outweighs its inertia
        # (Switches.damping_dominates: a 1 m cube at E 1e9, beta 0.1, pushed at 5 m/s, failed its solve
        # on 39 of 40 steps, each then a rigid step; now on 1), the line search holds the damping's frame
        # at the iterate it starts from (held_Bm), so that its E has the gradient's slope; the accepted
        # iterate's E_b is then taken in its own frame (body_shift), the next search's
        self.holds_frame = switches.stiffness_damping and (switches.contact or switches.damping_dominates)
        if self.holds_frame:
            self.held_Bm = ti.Matrix.field(3, 3, float, model.capacity.tets)
            self.body_shift = ti.field(ti.f64, nb)

    def coefficients(self, h):
        """(cM, cK) of H = cM M + cK K for the effective step h (s)."""
        return 1 + h * self.effects.alpha, h * self.effects.beta + h * h

    @ti.kernel
    def begin(self, x: ti.template(), v: ti.template(), last: ti.template()) -> ti.i32:
        """x0, v0 <- the step's start x_n, v_n (backward Euler's inertia target); the iterate x, v
        too (also how checks copy a state in). Returns how many positions differ from `last`
        (the solver's: where its last step ended)."""
        moved = 0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            moved += int((last[i] != x[i]).any())
            self.x0[i], self.v0[i] = x[i], v[i]
            self.x[i], self.v[i] = x[i], v[i]
        return moved

    # ------------------------------------------------------------ E

    @ti.kernel
    def energy(self, v0: ti.template(), x: ti.template(), v: ti.template(), h: float, moving: ti.i32):
        """E_b(v) of every body at x = x^ + h v into body_E (J, float64), with the rotations at
        x already extracted, and the tet terms of grad E there (gradient_vertices finishes it).
        moving=0: v is 0 (backward Euler's first iterate), so the damping terms are too.
        (Newton's kernels call its two passes themselves, with what comes next.)"""
        self.energy_vertices(x, v0, v, h)
        self.energy_tets(x, v, h, moving)

    @ti.func
    def iterate_energy(self, h, moving):
        """`energy` at the iterate x, v (with x^, v^ = x0, v0), inside another kernel."""
        self.energy_vertices(self.x, self.v0, self.v, h)
        self.energy_tets(self.x, self.v, h, moving)

    @ti.func
    def energy_vertices(self, x: ti.template(), v0: ti.template(), v: ti.template(), dt):
        """body_E[b] <- 1/2 |v_b - v^|_M^2 + dt alpha/2 |v_b|_M^2 - dt v_b^T M g + the ground's
        contact and friction terms, in float64 (J)."""
        self.sleep.sums.reduce(self.vertex_energy, self.store_energy, (x, v0, v, dt))
        if ti.static(self.effects.has_contact):          # the pairs' terms, and their gradient and Hessian
            self.effects.contact.evaluate(x, v, dt, self.body_E)

    @ti.func
    def vertex_energy(self, i, b, data: ti.template()):
        """Vertex i's terms of E (`energy_vertices`)."""
        x, v0, v = ti.static(data[0], data[1], data[2])
        dt = data[3]
        m = ti.cast(self.model.mass[i], ti.f64)
        u, u0 = ti.cast(v[i], ti.f64), ti.cast(v0[i], ti.f64)
        e = 0.5 * m * ((u - u0).norm_sqr() + dt * self.effects.mass_damping[None] * u.norm_sqr())
        if ti.static(self.has_gravity):
            e -= dt * m * u.dot(ti.cast(self.effects.gravity_vector(), ti.f64))
        if ti.static(self.effects.has_ground):
            e += self.effects.step_contact_energy(i, x[i]) + self.effects.friction_energy(i, v[i], dt)
        return ti.Vector([e, 0, 0, 0, 0, 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_energy(self, b, total, data: ti.template()):
        self.body_E[b] = total[0]

    @ti.func
    def energy_tets(self, x: ti.template(), v: ti.template(), dt, moving):
        """body_E[b] += Psi_b(x) + dt beta/2 v_b^T K(R) v_b, summed in float64 (J) over each
        body's tets in two stages (`Sleep.tet_sums`); corner <- the tet terms of grad E at
        (x, v), in the same pass: a trial iterate the line search accepts needs its gradient
        next. moving=0: v is 0 (as in gradient_corners), so the damping terms are too."""
        if ti.static(self.holds_frame):
            self.sleep.tet_pairs.reduce(self.tet_energy, self.add_energy, (x, v, dt, moving))
        else:
            self.sleep.tet_sums.reduce(self.tet_energy, self.add_energy, (x, v, dt, moving))

    @ti.func
    def tet_energy(self, e, b, data: ti.template()):
        """Tet e's terms of E; corner <- its terms of grad E."""
        x, v = ti.static(data[0], data[1])
        dt, moving = data[2], data[3]
        B = self.gradient_tet(x, v, dt, moving, e)
        awake = ti.cast(self.sleep.tet_awake(e), ti.f64)
        total = awake * self.elasticity.elastic_energy(x, e)
        own = ti.cast(0.0, ti.f64)                   # the damping in the iterate's own frame
        if ti.static(self.has_stiffness_damping):
            if moving:
                own = self.damping_energy(v, dt, e, B, awake)
        out = ti.Vector.zero(ti.f64, ti.static(2 if self.holds_frame else 1))
        out[0] = total + own
        if ti.static(self.holds_frame):              # the line search's E: the damping in the held frame
            held = ti.cast(0.0, ti.f64)
            if moving:
                held = self.damping_energy(v, dt, e, self.held_Bm[e], awake)
            out[0], out[1] = total + held, own - held
        return out

    @ti.func
    def damping_energy(self, v: ti.template(), dt, e, B, awake):
        """dt beta/2 v_e^T K v_e of tet e in the frame B = Bm R^T, float64 (J); 0 asleep (awake = 0)."""
        W = ti.cast(self.model.rest_volume[e], ti.f64)
        mu, lam = ti.cast(self.model.mu(e), ti.f64), ti.cast(self.model.lam(e), ti.f64)
        dF = ti.cast(self.model.edges(v, e), ti.f64) @ ti.cast(B, ti.f64)
        if self.rate_from_start[None]:
            dF += ti.cast(self.turn_rate(e, B, dt), ti.f64)
        beta = ti.cast(dt * self.effects.stiffness_damping[None], ti.f64)
        return awake * beta * W * energy_density(dF, mu, lam, 0.0)

    @ti.func
    def add_energy(self, b, total, data: ti.template()):
        self.body_E[b] += total[0]
        if ti.static(self.holds_frame):
            self.body_shift[b] = total[1]

    # ------------------------------------------------------------ grad E

    def gradient(self, v0, x, v, h, tolerance, first, moving=True):
        """-grad E at (x, v) into rhs; returns the weighted norm rho (converged: rho <= 1).
        first: the step's first iterate (it sets the scales); moving=False: v is 0."""
        self.gradient_corners(x, v, h, int(moving))
        return self.gradient_vertices(x, v0, v, h, tolerance, int(first), int(moving))

    @ti.kernel
    def gradient_corners(self, x: ti.template(), v: ti.template(), dt: float, moving: ti.i32):
        """corner <- the tet terms of grad E: -dt f_e(x) + dt beta (K(R) v)_e.
        moving=0: v is 0 (the step's first iterate), so the damping term is too."""
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.gradient_tet(x, v, dt, moving, e)

    @ti.func
    def gradient_tet(self, x: ti.template(), v: ti.template(), dt, moving, e):
        """corner <- tet e's terms of grad E (gradient_corners). Returns the Bm R^T its damping
        term used (0 without one), for energy_tets to reuse: R of the iterate, as the elastic
        term's, so that a rigid turn (dF = W F with W skew) has no strain rate."""
        W = self.model.rest_volume[e] * self.sleep.tet_awake(e)     # a sleeping body's tets add nothing
        self.elasticity.store_corners(e, corner_forces(-dt * self.elasticity.elastic_stress(x, e),
                                                       self.rotations.rotated_Bm[e], W))
        B = ti.Matrix.zero(float, 3, 3)
        if ti.static(self.has_stiffness_damping) and moving:
            B = self.rotations.rotated_Bm[e]
            dF = self.model.edges(v, e) @ B
            if ti.static(self.has_stiffness_damping):       # (the condition above is a run-time one)
                if self.rate_from_start[None]:
                    dF += self.turn_rate(e, B, dt)
            eps = 0.5 * (dF + dF.transpose())
            P = linear_stress(eps, self.model.mu(e), self.model.lam(e))
            f = corner_forces(-dt * self.effects.stiffness_damping[None] * P, B, W)
            for k in ti.static(range(4)):
                self.elasticity.corner[4 * e + k] += f[k]
        return B

    @ti.func
    def turn_rate(self, e, B, dt):
        """What backward Euler's damping adds to tet e's velocity gradient edges(v) Bm R^T (B = Bm R^T,
        R at the iterate) so that it is the rate of the tet's strain over the step in its rotated
        frame, (F - Q F_n) R^T / dt with Q = R R_n^T its turn: with F = F_n + dt edges(v) Bm, that is
        (I - Q) F_n R^T / dt. A backward Euler step's velocities are chords, (x - x_n) / dt: for a
        tet turning rigidly by Q they are no rotation rate at x, and the damping took them for a
        strain rate (a box at E 5e7 spinning at 3 rad/s kept 0.58 of its spin after one step with
        beta 0.1). The second-order rules' velocities are tangents, and need none of this."""
        Q = quaternion_matrix(self.rotations.quaternions[e]) @ quaternion_matrix(self.rotations.start[e]).transpose()
        FnRt = self.model.edges(self.x0, e) @ B
        return (FnRt - Q @ FnRt) / dt

    @ti.kernel
    def gradient_vertices(self, x: ti.template(), v0: ti.template(), v: ti.template(), dt: float,
                          tolerance: ti.f64, first: ti.i32, moving: ti.i32) -> ti.f64:
        """rhs <- -grad E at (x, v) from the tet terms in corner (`gather_gradient`); returns rho."""
        return self.gather_gradient(x, v0, v, dt, tolerance, first, moving)

    @ti.func
    def iterate_gradient(self, h, tolerance, first, moving):
        """`gather_gradient` at the iterate x, v, inside another kernel; returns rho."""
        return self.gather_gradient(self.x, self.v0, self.v, h, tolerance, first, moving)

    @ti.func
    def gather_gradient(self, x: ti.template(), v0: ti.template(), v: ti.template(), dt, tolerance, first,
                        moving):
        """rhs <- -grad E = M v^ + dt M g - (1 + dt alpha) M v - (gathered tet terms) + (the
        ground's), the per-body |grad_b|^2 and the per-body scale s_b^2 at this iterate (on the
        step's first call also |M v^|^2). Returns `gradient_norm` (moving: v is not 0)."""
        self.sleep.sums.reduce(self.vertex_gradient, self.store_gradient, (x, v0, v, dt, first))
        return self.gradient_norm(tolerance, first, moving)

    @ti.func
    def vertex_gradient(self, i, b, data: ti.template()):
        """rhs[i] <- vertex i's -grad E; returns its (|grad|^2, |M v^|^2, share of the scale)."""
        x, v0, v = ti.static(data[0], data[1], data[2])
        dt = data[3]
        m = self.model.mass[i]
        g = ti.Vector.zero(float, 3)
        if ti.static(self.has_gravity):
            g = dt * m * self.effects.gravity_vector()
        tets = self.elasticity.gather(i)
        if ti.static(self.effects.has_ground):       # with gravity's impulse in the step's scale
            g += self.effects.contact_force(i, x[i], v[i], dt)
        if ti.static(self.effects.has_contact):      # from the last energy pass at this iterate
            g += self.effects.contact.force[i]
        rhs = m * v0[i] + g - (1.0 + dt * self.effects.mass_damping[None]) * m * v[i] - tets
        self.rhs[i] = rhs
        # the scale, at this iterate: |M v^|^2 + |dt f|^2 + |dt M g|^2, not |rhs|^2 (~0 at rest).
        # Taken at the first iterate only, a guess that strains a stiff body inflated it 7 to
        # 5,500 times, and "converged" steps carried residuals that many times the tolerance
        momentum = ti.cast(self.effects.filtered(i, m * v0[i]).norm_sqr(), ti.f64)
        scale = momentum + ti.cast(self.effects.filtered(i, tets).norm_sqr() + self.effects.filtered(i, g).norm_sqr(),
                                   ti.f64)
        reach = ti.cast(m * x[i].norm_sqr(), ti.f64) * data[4]      # the step's first iterate: where it is
        return ti.Vector([ti.cast(self.effects.filtered(i, rhs).norm_sqr(), ti.f64), momentum, scale,
                          reach, ti.cast(m, ti.f64), 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_gradient(self, b, total, data: ti.template()):
        self.body_gradient[b], self.body_scale[b] = total[0], total[2]
        if data[4]:                                  # the step's first iterate
            self.body_momentum[b] = total[1]
            # A float32 position x carries a round-off of eps |x|: a body D from the origin has D / L
            # times the strain noise of one at the origin (L its size), and its gradient and velocity
            # changes that much more noise. Ten cubes 3 m apart (tests/test_energy.py's ground drops):
            # the one 21 m out, within its tolerance alone at the origin, jittered above the floors of
            # its size for 20 Newton iterations a step, and held every other body's step with it.
            far = ti.cast(1.0, ti.f64)
            if total[4] > 0 and self.body_size_sq[b] > 0:
                far = ti.max(far, total[3] / (total[4] * self.body_size_sq[b]))
            self.body_far[b] = far
            self.body_floor[b] = self.body_near_floor[b] * far

    @ti.func
    def gradient_norm(self, tolerance, first, moving):
        """max_b |grad_b|^2 / (tol^2 s_b^2 + floor_b): <= 1 exactly when every body has
        converged, relative to its own scale s_b or below its round-off floor. (Their sum was
        stricter than the bodies' own tests: fertility's two statues, each within its tolerance,
        reported 11 of 40 trapezoidal f32 steps unconverged at a sum of 1.02 to 1.94, and Newton,
        with nothing left to gain for either body, had stopped.)
        On the first call at v = 0 (not moving) a body whose momentum |M v_n| is above the floor
        counts as not converged: v = 0 is no answer for a moving body, even one so stiff (in f32)
        that its whole gradient is below the floor; it would stop dead. (From the guess, the
        gradient alone tells: a guess within the tolerance is the answer.)"""
        rho, total = ti.cast(0.0, ti.f64), ti.cast(0.0, ti.f64)
        self.relative[None] = 0.0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            allowed = tolerance * tolerance * self.body_scale[b] + self.body_floor[b] + self.effects.round_off(b)
            self.body_weight[b] = ti.cast(1.0 / allowed, float)
            if self.body_scale[b] > 0.0:
                self.relative[None] = ti.max(self.relative[None], self.body_gradient[b] / self.body_scale[b])
            ratio = self.body_gradient[b] / allowed
            if first and self.body_momentum[b] > self.body_floor[b] and not moving:
                ratio += 2.0
            self.body_ratio[b] = ratio
            rho = ti.max(rho, ratio)
            total += ratio
        return rho + 0.0 * total           # max drops a NaN; the sum keeps it (a broken step stays broken)

    # ------------------------------------------------------------ H u

    @ti.func
    def apply_H(self, i, u: ti.template(), cM, cK):
        """(H u)_i = cM m_i u_i + cK (K u)_i (+ the ground's block), filtered; K u gathered from
        the elasticity's corners."""
        Hu = cM * self.model.mass[i] * u[i] + cK * self.elasticity.gather(i)
        if ti.static(self.effects.has_ground):
            Hu += self.effects.contact_product(i, u)
        if ti.static(self.effects.has_contact):          # the pairs' share, from the last product pass
            Hu += self.effects.contact.product[i]
        return self.effects.filtered(i, Hu)
