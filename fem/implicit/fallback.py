"""What a trimmed body does instead of its step (fem/implicit/safeguards.py, `limit_energy`
decides which body): a rise the energy projection cannot pay for comes from a failed solve, and
the body takes a step whose energy is known. `Fallback` is Safeguards' share: its fields are
Safeguards'.
"""

import taichi as ti

from fem.runtime import has_f64_trigonometry

BEFORE, AFTER = 0, 1     # rows of Safeguards.body_total
STAY = 2                 # body_fallback: the trimmed body stays at x_n (`slowed`)
# A trimmed body whose elastic energy at the start was above this share of the size of its energy's
# terms (kinetic, elastic, |gravitational|), and above mu V STRAINED_STRAIN^2, is strained
# (`strained`): its step is taken again by backward Euler, not rigidly
STRAINED = 1e-3
STRAINED_STRAIN = 1e-3


@ti.data_oriented
class Fallback:
    """`fall_back`, `slowed` and `settle`, on the fields of fem.implicit.safeguards.Safeguards."""

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

        A free body takes a rigid step: its start shape x_n, turned by its start spin omega_n for
        dt about a centre that moves as the step's momentum says, c_n + dt (v_c,n + v_c,n+1) / 2,
        with the rigid velocities v_c,n+1 + omega_n x r. Its strains, and so its elastic energy,
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
            omega = self.body_spin[b]
            R = ti.Matrix.identity(ti.f64, 3)
            if self.model.body_method[b] == 0:    # a turned linear body is strained: it only translates
                self.body_spin[b] = ti.Vector.zero(ti.f64, 3)
            else:
                R = turn(omega * dt)
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
        failing; the solver takes the step again by backward Euler. A stiff body that moves as
        one (spinning or falling at E 1e10: strains of round-off, 1e-8 of its energy) and a body
        at rest with round-off's strain energy (1e-9 J) are not strained."""
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
            if self.body_fallback[b] and elastic > STRAINED * self.body_total_size[BEFORE, b] \
                    and elastic > STRAINED_STRAIN ** 2 * self.body_stiffness[b]:
                count += 1
        return count

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
def turn(phi):
    """The rotation by the angle |phi| about phi (float64), from its unit quaternion: orthogonal
    to round-off whatever precision the half angle's sine and cosine come in (float32 where the
    backend has no float64 trigonometry, such as Vulkan)."""
    half = 0.5 * phi.norm()
    c, s = ti.cast(1.0, ti.f64), ti.cast(0.0, ti.f64)
    if ti.static(has_f64_trigonometry()):
        c, s = ti.cos(half), ti.sin(half)
    else:
        c, s = ti.cast(ti.cos(ti.cast(half, ti.f32)), ti.f64), ti.cast(ti.sin(ti.cast(half, ti.f32)), ti.f64)
    q = ti.Vector([c, 0.0, 0.0, 0.0], ti.f64)
    if half > 0.0:
        a = s * phi / phi.norm()
        q = ti.Vector([c, a[0], a[1], a[2]], ti.f64)
    q /= q.norm()
    w, x, y, z = q[0], q[1], q[2], q[3]
    return ti.Matrix([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], ti.f64)
