"""What a trimmed body does instead of its step (fem/implicit/safeguards.py, `limit_energy`
decides which body): a rise the energy projection cannot pay for comes from a failed solve, and
the body takes a step whose energy is known. `Fallback` is Safeguards' share: its fields are
Safeguards'.
"""

import taichi as ti


BEFORE, AFTER = 0, 1     # rows of Safeguards.body_total
STAY = 2                 # body_fallback: the trimmed body stays at x_n (`slowed`)
# A trimmed body whose elastic energy at the start was above this share of the size of its energy's
# terms (kinetic, elastic, |gravitational|), and above mu V STRAINED_STRAIN^2, is strained
# (`strained`): after its rigid step the next step is backward Euler's (ImplicitSolver.step)
STRAINED = 1e-3
STRAINED_STRAIN = 1e-3
FREE_TURN_ITERATIONS = 40    # `free_turn`'s fixed point: each contracts by about dt |omega| (0.2 at 10 rad/s, dt 0.02 s)


@ti.data_oriented
class Fallback:
    """`fall_back`, `slowed` and `settle`, and each body's rigid motion (`rigid_motion`: its centre,
    spin and inertia), on the fields of fem.implicit.safeguards.Safeguards."""

    @ti.func
    def slowed(self, b, energy):
        """For `fall_back` on the ground: the factor on body b's velocities at the step's end that
        brings its energy there (`energy`) down to its energy BEFORE; where even its positions
        hold more than that, 0, and body_fallback[b] <- STAY: it stays at x_n."""
        kinetic = self.body_moving[b]
        budget = self.body_total[BEFORE, b] - (energy - kinetic)          # what its speed may hold
        s = ti.cast(0.0, ti.f64)
        if budget >= 0.0 and kinetic > 0.0:
            s = ti.sqrt(ti.min(budget / kinetic, 1.0))
        elif budget < 0.0:
            self.body_fallback[b] = STAY
        return s

    @ti.func
    def fall_back(self, x_n: ti.template(), v_n: ti.template(), x: ti.template(), v: ti.template(), dt):
        """A trimmed body takes a step whose energy is known instead. Only a failed solve gets
        here: a capped linear solve, or an integrator that cannot follow that body at this dt.

        A free body takes a rigid step: its start shape x_n, turned as a free rigid body with its
        start inertia and angular momentum turns (`free_turn`: both its angular momentum and its
        spin's kinetic energy kept exactly) about a centre that moves as the step's momentum says, c_n + dt (v_c,n + v_c,n+1) / 2,
        with the rigid velocities v_c,n+1 + omega' x r. Its strains, and so its elastic energy,
        are those it began with, its spin keeps its kinetic energy, its centre trades kinetic for
        gravitational energy exactly as the trapezoidal rule does, and only its deformation's
        kinetic energy goes: the energy cannot rise, and the body goes on moving (a stiff body,
        nearly rigid, moves as one). A linear body, whose energy a turn would strain, only
        translates. A body the ground touches (at the step's start or its failed end) could be
        carried into it by such a step (or is, where the step would press it in). It keeps the
        step's end instead, its velocities slowed by the one factor that brings its energy to
        the start's (`slowed`); where the end's positions alone hold more energy than that, no
        motion the step found lowers its energy (a stiff linear body turning on the ground: a
        turn strains it), and it stays at x_n, at rest. Either way its energy is at most the
        one it began with."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_spin_new[b] = self.centre_velocity(b)       # v_c,n+1, before rigid_motion(x_n) overwrites it
        self.rigid_motion(x_n, v_n)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            R = ti.Matrix.identity(ti.f64, 3)
            if self.model.body_method[b] == 0:    # a turned linear body is strained: it only translates
                self.body_spin[b] = ti.Vector.zero(ti.f64, 3)
            elif self.body_spin[b].norm() > 0.0:
                R, self.body_spin[b] = free_turn(self.body_inertia[b], self.body_spin[b], dt)
            self.body_inertia[b] = R                                  # reused: the turn
            self.body_shift_vector[b] = 0.5 * dt * (self.centre_velocity(b) + self.body_spin_new[b])
        if ti.static(self.effects.has_ground):      # would the rigid step reach into the ground?
            ti.loop_config(serialize=self.serial_vertices)
            for i in range(self.model.vertex_count[None]):
                b = self.model.vertex_body[i]
                if self.body_fallback[b] and self.effects.pressed(self.rigid_position(x_n, i, b)):
                    self.body_touching[b] = 1
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b, f = self.model.vertex_body[i], self.island(self.model.vertex_body[i])    # f: whose trim
            if self.body_fallback[f] and self.model.free[i] > 0 and (self.body_touching[f] or ti.static(self.effects.has_contact)):
                v[i] *= ti.cast(self.body_speed[f], float)
                if self.body_fallback[f] == STAY:     # no motion from here lowers its energy (a turned linear body)
                    x[i] = x_n[i]
            elif self.body_fallback[b] and self.model.free[i] > 0:
                r = self.body_inertia[b] @ (ti.cast(x_n[i], ti.f64) - self.body_centre[b])
                x[i] = self.rigid_position(x_n, i, b)
                v[i] = ti.cast(self.body_spin_new[b] + self.body_spin[b].cross(r), float)
            elif self.body_fallback[b]:
                x[i], v[i] = x_n[i], ti.Vector.zero(float, 3)

    @ti.kernel
    def settle(self, x_n: ti.template(), x: ti.template(), v: ti.template()):
        """After `fall_back` (rotations extracted at x): a trimmed body whose step still ends
        above its energy BEFORE (in f32, rounding the rigid step's positions strains a stiff
        body) is slowed by the one factor that takes the rise out of its kinetic energy; where
        that cannot (the rise is more than all of it), it stays at x_n, which holds no such
        rounding, its velocities slowed to its kinetic energy BEFORE. Either way: at most the
        energy it began with."""
        self.total_energy(x, v, AFTER, 1)
        self.rigid_motion(x, v)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            s = ti.cast(1.0, ti.f64)
            kinetic = self.body_kinetic[b] + 0.5 * self.centre_velocity(b).norm_sqr() * self.body_mass[b]
            rise = self.body_total[AFTER, b] - self.body_total[BEFORE, b]
            if self.body_fallback[b] and rise > self.allowance(b, self.body_total_size[AFTER, b]) and kinetic > 0.0:
                if rise < kinetic:                  # slowed a little, it goes on
                    s = ti.sqrt(1.0 - rise / kinetic)
                else:
                    s = -ti.sqrt(ti.min(1.0, self.body_kinetic_before[b] / kinetic))
                self.body_total[AFTER, b] = self.body_total[BEFORE, b]      # at most
            self.body_speed[b] = s
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if self.body_speed[b] != 1.0:
                v[i] *= ti.cast(ti.abs(self.body_speed[b]), float)
                if self.body_speed[b] < 0.0:
                    x[i] = x_n[i]

    @ti.func
    def strained(self):
        """The bodies trimmed this step that began it strained: holding elastic energy above
        STRAINED of the size of their energy's terms, and above that of a strain of
        STRAINED_STRAIN everywhere (mu V STRAINED_STRAIN^2): an inverted start, a strained body
        spinning at dt 0.5 s. A rigid step would keep that strain for as long as the solve keeps
        failing; the solver takes the next step by backward Euler. A stiff body that moves as
        one (spinning or falling at E 1e10: strains of round-off, 1e-8 of its energy) and a body
        at rest with round-off's strain energy (1e-9 J) are not strained. A body whose solve failed
        from rest and that stays at x_n (STAY) counts too: the next step would start where this one
        did and fail the same way (a 0.5 m cube at E 1e9 landing on the ground under the trapezoidal
        rule stayed frozen in the ground's penalty, every step a rigid one; tests/test_honest_steps.py).
        A moving body that stays does not: it goes on slowed, and a restart there cost more rigid
        steps than it saved (cube86 at nu 0.4999, dt 0.1 s, f32: 1 -> 11)."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_stiffness[b] = 0.0
        ti.loop_config(serialize=self.serial_tets)
        for e in range(self.model.tet_count[None]):
            b = self.model.tet_body[e]
            self.body_stiffness[b] += ti.cast(self.model.body_mu[b] * self.model.rest_volume[e], ti.f64)
        count = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            elastic = self.body_elastic_before[b]
            # a failed solve (not round-off) from rest, that leaves the body as it was: the next step would repeat it
            stays = self.body_fallback[b] == STAY and self.body_failed[b] and \
                self.body_kinetic_before[b] <= self.allowance(b, self.body_total_size[BEFORE, b])
            if stays or self.body_fallback[b] and elastic > STRAINED * self.body_total_size[BEFORE, b] \
                    and elastic > STRAINED_STRAIN ** 2 * self.body_stiffness[b]:
                count += 1
        return count

    # ------------------------------------------------------------ a body's rigid motion

    @ti.func
    def rigid_motion(self, x: ti.template(), v: ti.template()):
        """Per body: its centre's velocity (pinned: 0), its spin omega = I^-1 L (pinned: 0), the
        kinetic energy of its motion about the centre (body_kinetic) and of its deformation,
        v - v_cm - omega x r (body_deformation); free vertices only."""
        self.sleep.sums.reduce(self.moments, self.store_centre, (x, v))
        self.sleep.sums.reduce(self.turning, self.store_spin, (x, v))
        self.sleep.sums.reduce(self.deforming, self.store_deformation, (x, v))

    @ti.func
    def moments(self, i, b, data: ti.template()):
        """Free vertex i's (mass, momentum, first moment m x)."""
        x, v = ti.static(data[0], data[1])
        m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
        p, q = m * ti.cast(v[i], ti.f64), m * ti.cast(x[i], ti.f64)
        return ti.Vector([m, p[0], p[1], p[2], q[0], q[1], q[2], 0, 0, 0], ti.f64)

    @ti.func
    def store_centre(self, b, total, data: ti.template()):
        m = total[0]
        self.body_mass[b] = m
        self.body_momentum_vector[b] = ti.Vector([total[1], total[2], total[3]])
        self.body_centre[b] = ti.Vector([total[4], total[5], total[6]])
        if m > 0:
            self.body_centre[b] /= m

    @ti.func
    def turning(self, i, b, data: ti.template()):
        """Free vertex i's motion about its body's centre: (angular momentum m r x u, inertia
        m (r.r I - r r^T) as xx yy zz xy xz yz, kinetic energy m |u|^2 / 2)."""
        x, v = ti.static(data[0], data[1])
        m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
        r = ti.cast(x[i], ti.f64) - self.body_centre[b]
        u = ti.cast(v[i], ti.f64) - self.centre_velocity(b)
        L = m * r.cross(u)
        return ti.Vector([L[0], L[1], L[2],
                          m * (r[1] * r[1] + r[2] * r[2]), m * (r[0] * r[0] + r[2] * r[2]), m * (r[0] * r[0] + r[1] * r[1]),
                          -m * r[0] * r[1], -m * r[0] * r[2], -m * r[1] * r[2], 0.5 * m * u.norm_sqr()], ti.f64)

    @ti.func
    def store_spin(self, b, total, data: ti.template()):
        """omega = I^-1 L (pinned, or no inertia: 0)."""
        I = ti.Matrix([[total[3], total[6], total[7]], [total[6], total[4], total[8]], [total[7], total[8], total[5]]], ti.f64)
        omega = ti.Vector.zero(ti.f64, 3)
        if self.body_pinned[b] == 0 and I.determinant() > 1e-12 * I.trace() ** 3:
            omega = I.inverse() @ ti.Vector([total[0], total[1], total[2]])
        self.body_inertia[b], self.body_spin[b], self.body_kinetic[b] = I, omega, total[9]

    @ti.func
    def deforming(self, i, b, data: ti.template()):
        """Free vertex i's kinetic energy of deformation, m |v - v_c - omega x r|^2 / 2."""
        x, v = ti.static(data[0], data[1])
        m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
        w = self.deformation_velocity(b, ti.cast(x[i], ti.f64), ti.cast(v[i], ti.f64))
        return ti.Vector([0.5 * m * w.norm_sqr(), 0, 0, 0, 0, 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def deformation_velocity(self, b, x, v):
        """v at x less body b's rigid motion (`rigid_motion`): v - v_c - omega x (x - c), float64."""
        r = x - self.body_centre[b]
        return v - self.centre_velocity(b) - self.body_spin[b].cross(r)

    @ti.func
    def store_deformation(self, b, total, data: ti.template()):
        self.body_deformation[b] = total[0]
        self.body_moving[b] = self.body_kinetic[b] + 0.5 * self.centre_velocity(b).norm_sqr() * self.body_mass[b]

    @ti.kernel
    def arc_first_iterate(self, x_n: ti.template(), velocity: ti.template(), guess: ti.template(), h: float,
                          dt: float, from_guess: ti.i32) -> ti.i32:
        """The first Newton iterate moved to the rigid motion over dt of each free body too stiff
        for dt to follow: its shape at x_n turned by `free_turn` of its start's spin and inertia
        (`rigid_motion` BEFORE the step). Backward Euler's iterate is at x_n (v = 0): its centre
        moves by v_c dt. A multistep rule's iterate is its guess, x = x^ + h v: its centre stays
        the guess's, and only its shape is turned. x, v (the potential's iterate) and Newton's
        velocity and guess move by the same u. Returns how many bodies moved.

        From x_n, Newton's first step moves a turning body along its turn's tangent, which
        stretches every tet by (omega dt)^2 / 2, and so does a guess extrapolated linearly from
        v_n (v_n's own turn is a tangent, and BDF2's x^ a chord): Newton's quadratic model sees
        none of that, and a stiff body answers it with (lam + 2 mu) (omega dt)^2 / 2 of stress. A
        spinning cube at E 1e9, nu 0.49995 (3 rad/s, dt 0.02 s, f64) stalled at a relative
        residual of 1 for 20 iterations every step; from its arc it takes 2. Stiff means that
        sound crosses the body within about a step, (lam + 2 mu) dt^2 r >= M with r its radius of
        gyration (c dt >= 2.8 r for a cube): a soft body deforms through the step, and from its
        rigid motion Newton took more iterations than from x_n (scenes/cube86.toml, E 200 Pa and
        2 kPa)."""
        x, v = ti.static(self.potential.x, self.potential.v)
        stiff = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            stiff += self.stiff_turn(b, dt)
        self.sleep.sums.reduce(self.iterate_centre, self.store_iterate_centre, (x, x_n), int(stiff > 0))
        moved = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_arc[b] = ti.Matrix.identity(ti.f64, 3)
            if self.arc_turn(b, dt):
                R, _ = free_turn(self.body_inertia[b], self.body_spin[b], dt)
                self.body_arc[b] = R
                moved += 1
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None] * (moved > 0)):
            b = self.model.vertex_body[i]
            if self.model.free[i] > 0 and self.arc_turn(b, dt):
                r = ti.cast(x_n[i], ti.f64) - self.body_centre[b]
                u = ti.cast((self.body_arc[b] @ r - r) / dt + self.centre_velocity(b), float)
                if from_guess:                            # x = x^ + h v: to the guess's centre, turned
                    c = self.body_arc_centre[b]
                    turned = ti.Vector([c[0], c[1], c[2]]) + self.body_arc[b] @ r
                    u = ti.cast((turned - ti.cast(x[i], ti.f64)) / h, float)
                x[i] += h * u
                v[i] += u
                velocity[i] += u
                guess[i] += u
        return moved

    @ti.func
    def iterate_centre(self, i, b, data: ti.template()):
        """Free vertex i's (m x, m) at the iterate x, for its body's centre there, and 1 where it is
        pressed into the ground at x_n."""
        x, x_n = ti.static(data[0], data[1])
        m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
        y = ti.cast(x[i], ti.f64)
        return ti.Vector([m * y[0], m * y[1], m * y[2], m, ti.cast(self.effects.pressed(x_n[i]), ti.f64),
                          0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_iterate_centre(self, b, total, data: ti.template()):
        self.body_arc_centre[b] = ti.Vector([0.0, 0.0, 0.0, total[4]], ti.f64)
        if total[3] > 0:
            self.body_arc_centre[b] = ti.Vector([total[0] / total[3], total[1] / total[3], total[2] / total[3],
                                                 total[4]], ti.f64)

    @ti.func
    def arc_turn(self, b, dt):
        """Body b takes `arc_first_iterate`: too stiff for dt to follow (`stiff_turn`), and not
        pressed into the ground at the step's start (the ground, not its spin, decides its motion)."""
        return self.stiff_turn(b, dt) and self.body_arc_centre[b][3] == 0.0

    @ti.func
    def stiff_turn(self, b, dt):
        """Body b takes `arc_first_iterate`: free, awake, too stiff for dt to follow, and no further
        from its rest shape than twice its size L in its radius of gyration r (a body a huge impulse
        stretched to 1000 L moves as no rigid body; Model.any_stiff bounds r by that 2 L)."""
        M = self.body_mass[b]
        modulus = ti.cast(self.model.body_lam[b] + 2.0 * self.model.body_mu[b], ti.f64)
        r2 = 0.5 * self.body_inertia[b].trace() / M
        return M > 0 and self.body_pinned[b] == 0 and self.sleep.awake[b] != 0 and \
            r2 <= 4.0 * self.potential.body_size_sq[b] and modulus * dt * dt * ti.sqrt(r2) >= M

    @ti.func
    def centre_velocity(self, b):
        c = ti.Vector.zero(ti.f64, 3)
        if self.body_pinned[b] == 0 and self.body_mass[b] > 0:
            c = self.body_momentum_vector[b] / self.body_mass[b]
        return c

    @ti.func
    def rigid_position(self, x_n: ti.template(), i, b):
        """Where `fall_back`'s rigid step takes vertex i of body b."""
        r = self.body_inertia[b] @ (ti.cast(x_n[i], ti.f64) - self.body_centre[b])
        return ti.cast(self.body_centre[b] + self.body_shift_vector[b] + r, float)

    @ti.func
    def island(self, b):
        """The body whose entries hold body b's energy and limit: b itself, or body 0 where contact
        lets bodies trade energy (they are then one island, limited together)."""
        out = b
        if ti.static(self.effects.has_contact):
            out = 0
        return out


@ti.func
def cayley(phi):
    """The rotation (I - A / 2)^-1 (I + A / 2), A the cross-product matrix of phi (float64):
    exactly orthogonal, a turn by 2 atan(|phi| / 2) about phi."""
    A = ti.Matrix([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]], ti.f64)
    I = ti.Matrix.identity(ti.f64, 3)
    return (I - 0.5 * A).inverse() @ (I + 0.5 * A)


@ti.func
def free_turn(I, omega, dt):
    """A free rigid body's turn over dt that keeps its angular momentum L = I omega and its
    kinetic energy 1/2 omega.I omega exactly: (the turn R, the spin omega' after it), I its inertia
    at the start (kg m^2, world frame), omega its spin there (1/s, float64).

    Euler's equations in the body frame, dPi/dt = Pi x I^-1 Pi, by the implicit midpoint rule,
    which keeps both of their quadratic invariants |Pi|^2 and Pi.I^-1 Pi: Pi_1 = cay(-dt w) Pi_0
    with w = I^-1 (Pi_0 + Pi_1) / 2, found by fixed-point iterations (each contracts by about
    dt |omega|), and the body turned by R = cay(dt w), so that R Pi_1 = Pi_0: the angular momentum
    in the world frame is L_n. (Turning by omega_n dt with the spin kept, as before, changed an
    asymmetric body's L by 20 % in 2 s.)"""
    Pi0 = I @ omega
    Iinv = I.inverse()
    w = omega
    for _ in range(FREE_TURN_ITERATIONS):
        w = Iinv @ (0.5 * (Pi0 + cayley(-dt * w) @ Pi0))
    R = cayley(dt * w)
    return R, R @ (Iinv @ (cayley(-dt * w) @ Pi0))
