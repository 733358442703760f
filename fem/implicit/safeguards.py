"""What the step promises whatever the solve did: finite results, exact momentum, no energy gain.

- `check_finite`: a step whose result is not finite is rejected (the caller keeps its state).
- `restore_momentum`: an inexact solve leaves a residual whose sum is not zero, and internal
  forces can never change momentum: each unpinned body's velocity is shifted uniformly so
  that its momentum is exactly the integrator's (scenes without ground contact).
- `limit_energy`: backward Euler with a non-convex energy (corotated elasticity is not
  convex: a compressed tet's twist curvature is negative) can end a step with more energy
  than it began, even when solved exactly: thin, bending or buckling bodies do. The promise
  that total energy never rises is kept by a last safeguard: a body whose kinetic + elastic
  + gravitational energy rose has the velocities of its deformation (what is left of v once
  its centre's velocity and its rigid spin omega x r are taken out) scaled down by just
  enough, so that positions, momentum and angular momentum are untouched: a spinning body
  keeps its spin. Where its deformation holds less kinetic energy than the rise, its
  velocities relative to its centre of mass are scaled instead; a body whose rise is more
  than that motion holds (nearly at rest) keeps its old positions, at rest. A pinned body
  has no free centre or spin: its velocities are scaled. StepInfo counts all of these.
  A rise within round-off is no rise, and round-off is measured against the body's own
  history, not its current energy: a body's energy may wander up to ROUNDOFF eps of the
  largest size its energy's terms have had since the last change from outside (`start_band`)
  above the lowest energy it has had since then, and no further, so it can never climb, even
  by many small rises. (Measured against its current energy instead, a stiff body nearly at
  rest had every rise of its inexact, f32 solve of 1e-9 of its starting energy trimmed: a
  ratchet that took half the accuracy of the trapezoidal rule on the cube scene.) A limited
  body ends in the middle of that band, clear of the velocities' round-off.

Fields (bodies of the capacity; energies summed in float64):
    body_total (2, bodies)       each body's total energy [BEFORE, AFTER] the step, J
    body_total_size (2, bodies)  the sum of the sizes of its terms, J: the scale of its round-off
    body_mass (bodies,)          kg (free vertices only, for the energy limit)
    body_momentum_vector (bodies, 3)   kg m/s
    body_kinetic (bodies,)       J: kinetic energy relative to the centre of mass, then the
                                 factor its spin is scaled by (-1: the body goes back to x_n)
    body_deformation (bodies,)   J: the kinetic energy of its deformation, then the factor
                                 the deformation's velocities are scaled by
    body_centre (bodies, 3)      m: its centre of mass
    body_spin (bodies, 3)        its angular momentum about the centre (kg m^2/s), then omega (1/s)
    body_inertia (bodies, 3x3)   its inertia tensor about the centre, kg m^2
    body_pinned (bodies,)        1: the body has pinned vertices
    body_lowest (bodies,)        J: the lowest total energy it has had since the band started
    body_scale (bodies,)         J: the largest sum of its terms' sizes since then (-1: no band yet)
    body_elastic (bodies,)       its elastic energy when last summed, J: a step that starts where
                                 the last one ended (the same positions and rotations) reuses it
"""

import taichi as ti

from fem.elastic import is_finite
from fem.implicit.elasticity import TET_CHUNK
from fem.implicit.potential import ROUNDOFF
from fem.runtime import epsilon

BEFORE, AFTER = 0, 1     # rows of Safeguards.body_total
THREE_I32 = ti.types.vector(3, ti.i32)


@ti.data_oriented
class Safeguards:
    """The step's last checks for one model: energies from `elasticity` and `effects`
    (gravity), a sleeping body (`sleep`) left as it is."""

    def __init__(self, model, elasticity, effects, sleep, switches):
        nb = model.capacity.bodies
        self.model, self.elasticity, self.effects, self.sleep = model, elasticity, effects, sleep
        self.has_gravity = switches.gravity
        self.serial_tets, self.serial_vertices = switches.serial_tets, switches.serial_vertices
        self.body_total = ti.field(ti.f64, (2, nb))
        self.body_total_size = ti.field(ti.f64, (2, nb))
        self.body_mass = ti.field(ti.f64, nb)
        self.body_momentum_vector = ti.Vector.field(3, ti.f64, nb)
        self.body_kinetic = ti.field(ti.f64, nb)
        self.body_deformation = ti.field(ti.f64, nb)
        self.body_centre = ti.Vector.field(3, ti.f64, nb)
        self.body_spin = ti.Vector.field(3, ti.f64, nb)
        self.body_inertia = ti.Matrix.field(3, 3, ti.f64, nb)
        self.body_pinned = ti.field(ti.i32, nb)
        self.body_lowest = ti.field(ti.f64, nb)
        self.body_scale = ti.field(ti.f64, nb)
        self.body_elastic = ti.field(ti.f64, nb)
        self.forget_band()

    def forget_band(self):
        """The next step starts every body's band anew (a new state: `start_band`)."""
        self.body_scale.fill(-1.0)

    @ti.kernel
    def after_step(self, v0: ti.template(), x0: ti.template(), x_n: ti.template(), x: ti.template(),
                   v: ti.template(), h: float, dt: float, momentum: ti.template(),
                   energy: ti.template(), accel: ti.template(), keep: ti.template()) -> THREE_I32:
        """The step's last checks on its iterate x, v, in one launch: returns (vertices not
        finite, bodies energy-limited, how many of those were sent back to x_n). momentum:
        `restore_momentum`; energy: the total energy AFTER and `limit_energy` (x_n: the step's start). keep: accel <- the step's
        acceleration (v - v^) / h, what the forces did, before the energy limit takes any away
        (the trapezoidal rule's a_(n+1), fem/implicit/integrators.py). The caller discards a
        result that is not finite, whatever these did with it."""
        bad = self.check_finite(x, v)
        if ti.static(momentum):
            self.restore_momentum(v0, x0, x, v, h)
        if ti.static(keep):
            ti.loop_config(serialize=self.serial_vertices)
            for i in range(self.model.vertex_count[None]):
                accel[i] = (v[i] - v0[i]) / h
        limited = ti.Vector([0, 0], ti.i32)
        if ti.static(energy):
            self.total_energy(x, v, AFTER, 1)
            limited = self.limit_energy(x_n, x, v, dt, accel, keep)
        return ti.Vector([bad, limited[0], limited[1]], ti.i32)

    @ti.func
    def check_finite(self, x: ti.template(), v: ti.template()):
        """The count of vertices with a non-finite position or velocity."""
        bad = 0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if not is_finite(x[i].sum() + v[i].sum()):
                bad += 1
        return bad

    @ti.func
    def restore_momentum(self, v0: ti.template(), x0: ti.template(), x: ti.template(), v: ti.template(), dt):
        """Shift each unpinned body's velocity uniformly so that its momentum is exactly backward
        Euler's, (1 + dt alpha) sum m v = sum m v^ + dt M g."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_mass[b] = 0.0
            self.body_momentum_vector[b] = ti.Vector.zero(ti.f64, 3)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i], ti.f64)
            b = self.model.vertex_body[i]
            g = ti.Vector.zero(ti.f64, 3)
            if ti.static(self.has_gravity):
                g = dt * ti.cast(self.effects.gravity_vector(), ti.f64)
            self.body_mass[b] += m
            self.body_momentum_vector[b] += m * ((ti.cast(v0[i], ti.f64) + g)
                                                 / (1.0 + dt * self.effects.mass_damping[None])
                                                 - ti.cast(v[i], ti.f64))
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if self.body_pinned[b] == 0 and self.body_mass[b] > 0 and self.sleep.awake[b]:
                u = ti.cast(self.body_momentum_vector[b] / self.body_mass[b], float)
                v[i] += u
                x[i] = x0[i] + dt * v[i]

    @ti.kernel
    def body_energy(self, x: ti.template(), v: ti.template(), when: ti.template(), tets: ti.i32):
        """`total_energy` (tets=0: the elastic energies of the last sum, for the same x and R);
        BEFORE a step, `start_band` too."""
        self.total_energy(x, v, when, tets)
        if ti.static(when == BEFORE):
            self.start_band()

    @ti.func
    def start_band(self):
        """Each body's band before a step: started anew at its energy BEFORE where it has none or
        the energy is above the band (work from outside: an impulse, a live edit), else its
        lowest energy and its largest size so far."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            energy, size = self.body_total[BEFORE, b], self.body_total_size[BEFORE, b]
            if self.body_scale[b] < 0.0 or energy > self.body_lowest[b] + self.allowance(b, size):
                self.body_lowest[b], self.body_scale[b] = energy, size
            else:
                self.body_lowest[b] = ti.min(self.body_lowest[b], energy)
                self.body_scale[b] = ti.max(self.body_scale[b], size)

    @ti.func
    def allowance(self, b, size):
        """How far body b's energy may wander above its lowest: ROUNDOFF eps of its scale (J)."""
        return ti.static(ROUNDOFF * epsilon()) * ti.max(self.body_scale[b], size)

    @ti.func
    def total_energy(self, x: ti.template(), v: ti.template(), when, tets):
        """body_total[when, b] <- kinetic + elastic + gravitational (+ the ground's contact) energy
        of body b (J, float64),
        elastic with the rotations extracted at x (kept in body_elastic; tets=0: taken from it);
        body_total_size[when, b] <- the sum of the sizes of its terms (J), the scale of its
        round-off. when: BEFORE or AFTER the step."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if tets:
                self.body_elastic[b] = 0.0
        # A body's tets are contiguous: each chunk of tets sums into a running total and adds it
        # to body_elastic once per body it meets, not once per tet (threads would fight over it).
        n = self.model.tet_count[None]
        ti.loop_config(serialize=self.serial_tets)
        for c in range(tets * ((n + TET_CHUNK - 1) // TET_CHUNK)):
            body, elastic = -1, ti.cast(0.0, ti.f64)
            for e in range(c * TET_CHUNK, ti.min(n, (c + 1) * TET_CHUNK)):
                if self.model.tet_body[e] != body:
                    if body >= 0:
                        self.body_elastic[body] += elastic
                    body, elastic = self.model.tet_body[e], 0.0
                elastic += self.elasticity.elastic_energy(x, e)
            if body >= 0:
                self.body_elastic[body] += elastic
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_total[when, b], self.body_total_size[when, b] = 0.0, 0.0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_total[when, self.island(b)] += self.body_elastic[b]
            self.body_total_size[when, self.island(b)] += self.body_elastic[b]
        if ti.static(self.effects.has_contact):
            self.effects.contact.share_energy(x)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i], ti.f64)
            kinetic, potential = 0.5 * m * ti.cast(v[i], ti.f64).norm_sqr(), ti.cast(0.0, ti.f64)
            if ti.static(self.has_gravity):
                potential = -m * ti.cast(self.effects.gravity_vector(), ti.f64).dot(ti.cast(x[i], ti.f64))
            if ti.static(self.effects.has_ground):
                kinetic += self.effects.contact_energy(i, x[i])      # stored in the ground's penalty
            if ti.static(self.effects.has_contact):
                kinetic += self.effects.contact.energy[i]             # its share of the pairs' penalty
            self.body_total[when, self.island(self.model.vertex_body[i])] += kinetic + potential
            self.body_total_size[when, self.island(self.model.vertex_body[i])] += kinetic + ti.abs(potential)

    @ti.func
    def limit_energy(self, x0: ti.template(), x: ti.template(), v: ti.template(), dt, accel: ti.template(),
                     keep: ti.template()):
        """Take each rise out of the body's deformation, or else its motion about its centre
        (module docstring; x0: the step's start). keep: a body sent back to x0 gets accel <- 0,
        the step's is not for x0. Returns how many bodies were limited, and how many of them
        were sent back to x0 (the others keep their positions, so their elastic energies and
        rotations are still those at x)."""
        self.rigid_motion(x, v)
        limited, sent_back = 0, 0
        if ti.static(self.effects.has_contact):                # one island: body 0's entries hold the sums
            ti.loop_config(serialize=True)
            for b in range(1, self.model.body_count[None]):
                self.body_deformation[0] += self.body_deformation[b]
                self.body_kinetic[0] += self.body_kinetic[b]
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            energy, allowance = self.body_total[AFTER, b], self.allowance(b, self.body_total_size[AFTER, b])
            spin, deformation = ti.cast(1.0, ti.f64), ti.cast(1.0, ti.f64)
            if energy <= self.body_lowest[b] + allowance:     # a rise within round-off is no rise
                self.body_lowest[b] = ti.min(self.body_lowest[b], energy)
            else:                                              # down to the middle of the band
                rise = energy - self.body_lowest[b] - 0.5 * allowance
                limited += 1
                if self.body_deformation[b] > rise:
                    deformation = ti.sqrt(1.0 - rise / self.body_deformation[b])
                elif self.body_kinetic[b] > rise:
                    spin = ti.sqrt(1.0 - rise / self.body_kinetic[b])
                    deformation = spin
                else:
                    spin = -1.0                  # cannot be absorbed: keep x_n, at rest
                    sent_back += 1
            self.body_kinetic[b], self.body_deformation[b] = spin, deformation   # reused: the factors
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b, f = self.model.vertex_body[i], self.island(self.model.vertex_body[i])    # f: whose factors
            if self.body_kinetic[f] < 0.0:
                c = ti.Vector.zero(float, 3)       # gravity or the ground may have sped the centre up
                if ti.static(not (self.has_gravity or self.effects.has_ground)):
                    c = ti.cast(self.centre_velocity(b), float) * self.model.free[i]
                x[i], v[i] = x0[i] + dt * c, c
                if ti.static(keep):
                    accel[i] = ti.Vector.zero(float, 3)
            elif self.body_deformation[f] < 1.0:
                c = self.centre_velocity(b)
                turn = self.body_spin[b].cross(ti.cast(x[i], ti.f64) - self.body_centre[b])
                w = ti.cast(v[i], ti.f64) - c - turn
                u = c + self.body_kinetic[f] * turn + self.body_deformation[f] * w
                v[i] = ti.cast(u * self.model.free[i], float)
        return ti.Vector([limited, sent_back], ti.i32)

    @ti.func
    def island(self, b):
        """The body whose entries hold body b's energy and limit: b itself, or body 0 where contact
        lets bodies trade energy (they are then one island, limited together)."""
        out = b
        if ti.static(self.effects.has_contact):
            out = 0
        return out

    @ti.func
    def rigid_motion(self, x: ti.template(), v: ti.template()):
        """Per body: its centre's velocity (pinned: 0), its spin omega = I^-1 L (pinned: 0), the
        kinetic energy of its motion about the centre (body_kinetic) and of its deformation,
        v - v_cm - omega x r (body_deformation); free vertices only."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_mass[b] = 0.0
            self.body_momentum_vector[b] = ti.Vector.zero(ti.f64, 3)
            self.body_centre[b] = ti.Vector.zero(ti.f64, 3)
            self.body_spin[b] = ti.Vector.zero(ti.f64, 3)
            self.body_inertia[b] = ti.Matrix.zero(ti.f64, 3, 3)
            self.body_kinetic[b] = 0.0
            self.body_deformation[b] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
            b = self.model.vertex_body[i]
            self.body_mass[b] += m
            self.body_momentum_vector[b] += m * ti.cast(v[i], ti.f64)
            self.body_centre[b] += m * ti.cast(x[i], ti.f64)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.body_mass[b] > 0:
                self.body_centre[b] /= self.body_mass[b]
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):     # the motion about the centre: L, I, its energy
            b = self.model.vertex_body[i]
            m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
            r = ti.cast(x[i], ti.f64) - self.body_centre[b]
            u = ti.cast(v[i], ti.f64) - self.centre_velocity(b)
            self.body_spin[b] += m * r.cross(u)
            self.body_inertia[b] += m * (r.dot(r) * ti.Matrix.identity(ti.f64, 3) - r.outer_product(r))
            self.body_kinetic[b] += 0.5 * m * u.norm_sqr()
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            I = self.body_inertia[b]
            omega = ti.Vector.zero(ti.f64, 3)
            if self.body_pinned[b] == 0 and I.determinant() > 1e-12 * I.trace() ** 3:
                omega = I.inverse() @ self.body_spin[b]
            self.body_spin[b] = omega
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
            r = ti.cast(x[i], ti.f64) - self.body_centre[b]
            w = ti.cast(v[i], ti.f64) - self.centre_velocity(b) - self.body_spin[b].cross(r)
            self.body_deformation[b] += 0.5 * m * w.norm_sqr()

    @ti.func
    def centre_velocity(self, b):
        c = ti.Vector.zero(ti.f64, 3)
        if self.body_pinned[b] == 0 and self.body_mass[b] > 0:
            c = self.body_momentum_vector[b] / self.body_mass[b]
        return c
