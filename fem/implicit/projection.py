"""The energy projection's move of positions (docs/method.md, section 6, "The energy
projection"): a rise that scaling a body's deformation velocities cannot pay for is paid by its
deformation's positions, along the nearest-point direction of FEPR (Dinev et al. 2018)
restricted to the body's internal motion, so that its centre, momentum and angular momentum stay
the integrator's. `InternalMove` is Safeguards' share (fem/implicit/safeguards.py decides which
body, `limit_energy`); its fields are made by `make_move_fields`.

FEPR's Gauss-Newton step moves the state along the constraints' gradient; restricted to the
internal motion (what moves no centre and turns no body: the mass-weighted mean and rigid turn
taken out) the energy's is M w in v (the velocities' scale, `limit_energy`) and, in x, the
internal part of -(grad Psi - M g), which is M d with d = M^-1 f's internal part, f = -grad Psi
the elastic forces: uniform gravity moves only the centre. A move x + mu d lowers Psi by
mu |f|^2_M^-1 to first order. The move pays all of the rise but the velocities' first-order share
of the nearest point in the norm |dx|^2_M / dt^2 + |dv|^2_M, 2 K_w / (2 K_w + dt^2 |f|^2_M^-1),
at most a quarter of K_w (half of what the scale may take), and mu is found on Psi itself, with
the rotations extracted at each trial: Psi at the first-order mu fits Psi's curvature along d,
and the second mu is where that quadratic reaches the move's share. What is left over, either
way, the velocities' scale pays at the moved positions, where the spin is reset to L_n again.
"""

import taichi as ti

from fem.elastic import corner_forces
from fem.implicit.fallback import AFTER, BEFORE

PENDING = 3              # body_fallback: its rise waits for the move (Safeguards.limit_energy)
# A rise of more than this share of what the projection can take out is a failed solve, not
# round-off: scaling a blown-up step's deformation (1.5e10 J made from 0.67 J) back by 1 - lam
# left 2e3 J where the formula said 0 (the sliver hard case, f32, dt 0.5 s)
FAILED = 0.5
# `spin_by_law` corrects a drift: a body whose angular momentum the step changed by more than this
# share of the drag's (a wild step's: the hard cases' sliver, a pushed cube at E 1e9) keeps its spin
DRIFT = 0.1
# ... and so does a body whose gradient at the answer is above NEAR of its scale s (and round-off):
# its step is not the rule's (the hard cases' cube at nu 0.4999 and dt 0.5 s, 0.02 to 0.8 on every
# step, turned as round-off said once its spin was kept; the cube at E 1e8 stays within 5e-4 on 48
# of its 50 steps). Not relative to the tolerance: fertility at 1e-8 in float64 and 1e-4 in float32
# must take the same law
NEAR = 1e-3


@ti.data_oriented
class InternalMove:
    """`move_positions`, on the fields of fem.implicit.safeguards.Safeguards."""

    def make_move_fields(self, nb, nv):
        """body_move (bodies, 4): (the rise J, K_w J (+ the spin's kinetic energy where it may pay),
        F2 = |f|^2_M^-1 J/s^2, -), then (mu s^2, F2, Psi at mu = 0 J, the share the move pays J),
        then the change of mu, and last the band of `solve_band` (J) in its fourth;
        body_lightest (bodies,): 1 / m_min of its free vertices, 1/kg (`solve_band`);
        move_direction (vertices, 3): d, m/s^2 (a force per mass)."""
        self.body_move = ti.Vector.field(4, ti.f64, nb)
        self.body_lightest = ti.field(ti.f64, nb)
        self.solve_tolerance = ti.field(ti.f64, ())     # the tolerance the step's solve met (`solve_band`)
        self.tolerance = 0.0                            # what solve_tolerance holds
        self.move_direction = ti.Vector.field(3, float, nv)
        self.spin_law = ti.field(ti.f64, ())            # `spin_by_law`'s factor (0: the spin stays)
        self.law = 0.0                                  # what spin_law holds

    def keep_spin_by(self, law):
        """The damped theta rule's angular momentum, L_(n+1) = law L_n (`spin_by_law`; law 0: none),
        one launch where it changes."""
        if law != self.law:
            self.spin_law[None], self.law = law, law

    @ti.func
    def keeps_spin(self, b):
        """Body b's angular momentum is the scheme's to keep: no pins, forces that turn with it (not
        linear FEM's), and an inertia that can be inverted."""
        I = self.body_inertia[b]
        return self.body_pinned[b] == 0 and self.model.body_method[b] != 0 and I.determinant() > 1e-12 * I.trace() ** 3

    @ti.func
    def spin_by_law(self, b, rise):
        """With stiffness damping the energy-momentum step is not taken (docs/method.md, section 6), and
        the damped theta rule alone lets a spinning body's angular momentum go, where no internal force
        can change it: a stiff body's rule rings the modes dt cannot follow and the damping takes the spin
        out through them (a 0.5 m cube at E 1e8 and 10 rad/s, beta 0.01, kept 0.81 of it after 1 s), and
        under nonlinear forces the rule keeps no L even where dt follows them (at E 1e5, 0.959). The
        body's spin is set to what the drag leaves, I^-1 law L_n (`keep_spin_by`), where the deformation's
        velocities can pay for the energy that gives back (rise J, the body's rise above its lowest
        energy before it, plus the gain, at most FAILED K_w). Returns the kinetic energy gained, J."""
        gain = ti.cast(0.0, ti.f64)
        I, omega, L = self.body_inertia[b], self.body_spin[b], self.spin_law[None] * self.body_spin_before[b]
        p = self.potential                                  # |grad| within NEAR s, or round-off
        near = p.body_gradient[b] <= NEAR * NEAR * p.body_scale[b] + p.body_floor[b]
        if self.spin_law[None] > 0 and near and self.keeps_spin(b) and (L - I @ omega).norm() <= DRIFT * L.norm():
            turn = I.inverse() @ L - omega
            slope, curve = omega.dot(I @ turn), turn.dot(I @ turn)      # the gain of omega + s turn: s slope + s^2 curve / 2
            room = FAILED * self.body_deformation[b] - rise
            s = 1.0
            if slope + 0.5 * curve > room:       # the largest s whose gain fits, in the form that does not cancel
                s = 2.0 * room / (slope + ti.sqrt(ti.max(slope * slope + 2.0 * curve * room, 0.0))) if room > 0 else 0.0
            gain, self.body_spin_new[b] = s * slope + 0.5 * s * s * curve, omega + s * turn
        return gain

    @ti.func
    def movable(self, b):
        """Body b's positions may pay a rise: a free body (no pins) the ground does not touch, with
        no contact between bodies, awake."""
        yes = self.body_pinned[b] == 0 and self.body_touching[b] == 0 and self.sleep.awake[b] != 0
        if ti.static(self.effects.has_contact):
            yes = False
        return yes

    def move_positions(self, start, dt, conserve, tolerance, rotations_at):
        """The pending bodies' positions moved by their share of the rise, then the projection again
        at the moved positions (`limit_energy`, final): returns (bodies trimmed, bodies that took a
        rigid step, of those the strained, ms) as `after_step`'s. tolerance: the one every body's
        solve met (0: some body's did not; `solve_band`); rotations_at(x): re-extracts the
        rotations at x (the solver's), returns its ms."""
        if tolerance != self.tolerance:
            self.tolerance = self.solve_tolerance[None] = tolerance
        self.first_move(dt)
        ms = rotations_at(self.potential.x)
        self.second_move()
        ms += rotations_at(self.potential.x)
        counts = self.after_move(start, dt, conserve)
        return int(counts[0]), int(counts[1]), int(counts[2]), ms

    @ti.kernel
    def first_move(self, dt: float):
        """d of every pending body at the iterate x (its elastic forces, with the rotations at x),
        and x <- x + mu_1 d, mu_1 its first-order share."""
        x = ti.static(self.potential.x)
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            self.elasticity.store_corners(e, corner_forces(self.elasticity.elastic_stress(x, e),
                                                         self.elasticity.rotations.rotated_Bm[e], self.model.rest_volume[e]))
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            d = ti.Vector.zero(float, 3)
            if self.body_fallback[b] == PENDING and self.model.mass[i] > 0:
                d = self.elasticity.gather(i) / self.model.mass[i] * self.model.free[i]
            self.move_direction[i] = d
        # out of d: its mean (it moves the centre) and its rigid turn (it turns the body, Psi stays)
        self.sleep.sums.reduce(self.direction_moments, self.store_direction, x)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if self.body_fallback[b] == PENDING:
                r = ti.cast(x[i], ti.f64) - self.body_centre[b]
                mean, turn = self.body_spin_new[b], self.body_shift_vector[b]
                d = ti.cast(self.move_direction[i], ti.f64) - mean - turn.cross(r)
                self.move_direction[i] = ti.cast(d * self.model.free[i], float)
        self.sleep.sums.reduce(self.direction_size, self.store_size, x)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.body_fallback[b] == PENDING:
                rise, K, F2 = self.body_move[b][0], self.body_move[b][1], self.body_move[b][2]
                share = rise
                if K > 0.0:       # the velocities' first-order share, at most half what they may take
                    share -= ti.min(rise * 2.0 * K / (2.0 * K + dt * dt * F2), 0.25 * K)
                mu = ti.cast(0.0, ti.f64)
                if F2 > 0.0:
                    mu = share / F2
                self.body_move[b] = ti.Vector([mu, F2, self.body_elastic[b], share])
        self.step_along(1)

    @ti.kernel
    def second_move(self):
        """Psi at mu_1 fits Psi's curvature c along d: Psi(mu) = Psi_0 - mu F2 + c mu^2 / 2; mu_2
        is where that lowers Psi by the share (or its lowest point, where none does)."""
        self.sleep.tet_sums.reduce(self.tet_elastic, self.store_elastic, self.potential.x, 1)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.body_fallback[b] == PENDING:
                mu, F2, psi0, share = self.body_move[b][0], self.body_move[b][1], self.body_move[b][2], self.body_move[b][3]
                c = ti.cast(0.0, ti.f64)
                if mu > 0.0:
                    c = 2.0 * (self.body_elastic[b] - psi0 + mu * F2) / (mu * mu)
                again = mu
                if c > 0.0:
                    disc = F2 * F2 - 2.0 * c * share
                    again = F2 / c
                    if disc >= 0.0:
                        again = 2.0 * share / (F2 + ti.sqrt(disc))
                self.body_move[b][0] = again - mu
        self.step_along(0)

    @ti.func
    def step_along(self, first):
        """x <- x + body_move[0] d (first: the first mu; then the change of mu) on pending bodies."""
        x = ti.static(self.potential.x)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if self.body_fallback[b] == PENDING:
                x[i] += ti.cast(self.body_move[b][0], float) * self.move_direction[i]

    @ti.kernel
    def after_move(self, start: ti.template(), dt: float, conserve: ti.i32) -> ti.types.vector(3, ti.i32):
        """The projection again, at the moved positions (`Safeguards.limit_energy`, final): a rise
        the velocities' scale still cannot pay for is a failed solve: the body takes the rigid step."""
        x, v = ti.static(self.potential.x, self.potential.v)
        self.sleep.fastest.reduce(self.lightest, self.solve_band, x)
        self.total_energy(x, v, AFTER, 1)
        counts = self.limit_energy(x, v, conserve, 1)
        strained = 0
        if counts[1] > 0:
            strained = self.strained()
            self.fall_back(start.x, start.v, x, v, dt)
        return ti.Vector([counts[0], counts[1], strained], ti.i32)

    @ti.func
    def lightest(self, i, b, data: ti.template()):
        """1 / m_i of free vertex i (0 where pinned)."""
        return ti.Vector([self.model.free[i] / self.model.mass[i], 0.0], ti.f64)

    @ti.func
    def solve_band(self, b, largest, data: ti.template()):
        """body_move[b][3] <- the energy error body b's solve may leave in its deformation (J): its
        residual r, |r| <= tol s_b (potential.body_scale: s_b^2), gives its velocities an error dv
        with |dv|_M <= |r|_M^-1 <= tol s_b / sqrt(m_min), whose kinetic energy, and about as much
        strain energy, is at most tol^2 s_b^2 / m_min. A rise within it that neither its
        deformation's velocities nor positions could pay for (a body whose deformation holds
        nothing but that error: one released at rest) is no failed solve."""
        self.body_move[b][3] = self.solve_tolerance[None] ** 2 * self.potential.body_scale[b] * largest[0]
        self.body_lightest[b] = largest[0]
        # (a solve that did not converge promises no tolerance: its band is 0)

    @ti.func
    def band(self, b, K, conserve, rise):
        """The rise body b's solve may leave (J): `solve_band`'s, and under the conserving scheme the
        share of the round-off floors its gradient converged within (potential.gradient_norm), |r_floor|^2 <=
        floor_b: the energy-momentum step changes the energy by exactly -sum r . (x - x_n) / dt, and
        the rigid motion's share is put right, so what is left is |r . w| <= |r|_M^-1 |w|_M <=
        sqrt(2 floor_b K_w / m_min), w the deformation's velocities (K_w their kinetic energy). A
        stiff float32 body stops at what float32 resolves: the 0.5 m cube at E 1e8 spinning at 10.3
        rad/s took a rigid step on 23 of 100 steps for it (docs/method.md, section 6). Not for a rise
        (above round-off's allowance) within what round-off gives a body at rest (`body_quiet`): its
        rigid step keeps it still, where the step's round-off motion would cost a solve each step after.
        A body that met its tolerance only within its floor (its gradient above tol^2 s_b^2) promises
        no more than the tolerance's share of its energy at the step's start, 2 tol (the sizes of its
        terms): its scale s_b, taken at the answer, grows with the strain the answer left (a float32
        0.5 m cube at E 1e11, nu 0.4999, spinning at 10 rad/s: a band of 274 J let its energy rise
        from 402 to 658 J in one step)."""
        tol, out = self.solve_tolerance[None], self.body_move[b][3]
        if conserve and tol > 0 and rise > self.body_quiet[b] * self.potential.body_far[b]:
            floor = self.potential.body_floor[b] + self.effects.round_off(b)
            out += ti.sqrt(2.0 * floor * self.body_lightest[b] * ti.max(K, 0.0))
        if self.potential.body_gradient[b] > tol * tol * self.potential.body_scale[b]:
            out = ti.min(out, 2.0 * tol * self.body_total_size[BEFORE, b])
        return out

    @ti.func
    def direction_moments(self, i, b, data: ti.template()):
        """Free vertex i's (m d, m r x d) for the mean and the rigid turn of d."""
        x = ti.static(data)
        m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
        d = ti.cast(self.move_direction[i], ti.f64)
        r = ti.cast(x[i], ti.f64) - self.body_centre[b]
        q = m * r.cross(d)
        return ti.Vector([m * d[0], m * d[1], m * d[2], q[0], q[1], q[2], 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_direction(self, b, total, data: ti.template()):
        """The mean of d into body_spin_new, its rigid turn I^-1 (sum m r x d) into body_shift_vector
        (free for the move: `fall_back` writes them later)."""
        mean, turn = ti.Vector.zero(ti.f64, 3), ti.Vector.zero(ti.f64, 3)
        I = self.body_inertia[b]
        if self.body_mass[b] > 0:
            mean = ti.Vector([total[0], total[1], total[2]]) / self.body_mass[b]
        if I.determinant() > 1e-12 * I.trace() ** 3:
            turn = I.inverse() @ ti.Vector([total[3], total[4], total[5]])
        self.body_spin_new[b], self.body_shift_vector[b] = mean, turn

    @ti.func
    def direction_size(self, i, b, data: ti.template()):
        """Free vertex i's m |d|^2 = |f_i|^2 / m."""
        m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
        return ti.Vector([m * ti.cast(self.move_direction[i], ti.f64).norm_sqr(), 0, 0, 0, 0, 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_size(self, b, total, data: ti.template()):
        self.body_move[b][2] = total[0]
