"""What the step promises whatever the solve did: finite results, exact momentum, no energy gain.

- `check_finite`: a step whose result is not finite is rejected (the caller keeps its state).
- `restore_momentum`: an inexact solve leaves a residual whose sum is not zero, and internal
  forces can never change momentum: each unpinned body's velocity is shifted uniformly so
  that its momentum is exactly the integrator's (scenes without ground contact).
- `limit_energy`: backward Euler with a non-convex energy (corotated elasticity is not
  convex: a compressed tet's twist curvature is negative) can end a step with more energy
  than it began, even when solved exactly: thin, bending or buckling bodies do. The promise
  that total energy never rises is kept by a last safeguard: a body whose kinetic + elastic
  + gravitational energy rose has its velocities relative to its centre of mass scaled down
  by just enough (positions and linear momentum untouched); a body whose rise is more than
  that motion holds (nearly at rest) keeps its old positions, at rest. StepInfo counts both.

Fields (bodies of the capacity; energies summed in float64):
    body_total (2, bodies)       each body's total energy [BEFORE, AFTER] the step, J
    body_total_size (2, bodies)  the sum of the sizes of its terms, J: the scale of its round-off
    body_mass (bodies,)          kg (free vertices only, for the energy limit)
    body_momentum_vector (bodies, 3)   kg m/s
    body_kinetic (bodies,)       J: kinetic energy relative to the centre of mass, then the
                                 factor its relative velocities are scaled by
    body_pinned (bodies,)        1: the body has pinned vertices
    body_elastic (bodies,)       its elastic energy when last summed, J: a step that starts where
                                 the last one ended (the same positions and rotations) reuses it
"""

import taichi as ti

from fem.elastic import is_finite
from fem.implicit.elasticity import TET_CHUNK
from fem.implicit.potential import ROUNDOFF
from fem.runtime import epsilon

BEFORE, AFTER = 0, 1     # rows of Safeguards.body_total
TWO_I32 = ti.types.vector(2, ti.i32)


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
        self.body_pinned = ti.field(ti.i32, nb)
        self.body_elastic = ti.field(ti.f64, nb)

    @ti.kernel
    def after_step(self, v0: ti.template(), x0: ti.template(), x_n: ti.template(), x: ti.template(),
                   v: ti.template(), h: float, dt: float, momentum: ti.template(),
                   energy: ti.template(), accel: ti.template(), keep: ti.template()) -> TWO_I32:
        """The step's last checks on its iterate x, v, in one launch: returns (vertices not
        finite, bodies energy-limited). momentum: `restore_momentum`; energy: the total
        energy AFTER and `limit_energy` (x_n: the step's start). keep: accel <- the step's
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
        limited = 0
        if ti.static(energy):
            self.total_energy(x, v, AFTER, 1)
            limited = self.limit_energy(x_n, x, v, dt, accel, keep)
        return ti.Vector([bad, limited], ti.i32)

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
    def body_energy(self, x: ti.template(), v: ti.template(), when: ti.i32, tets: ti.i32):
        """`total_energy` (tets=0: the elastic energies of the last sum, for the same x and R)."""
        self.total_energy(x, v, when, tets)

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
            self.body_total[when, b], self.body_total_size[when, b] = self.body_elastic[b], self.body_elastic[b]
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i], ti.f64)
            kinetic, potential = 0.5 * m * ti.cast(v[i], ti.f64).norm_sqr(), ti.cast(0.0, ti.f64)
            if ti.static(self.has_gravity):
                potential = -m * ti.cast(self.effects.gravity_vector(), ti.f64).dot(ti.cast(x[i], ti.f64))
            if ti.static(self.effects.has_ground):
                kinetic += self.effects.contact_energy(i, x[i])      # stored in the ground's penalty
            self.body_total[when, self.model.vertex_body[i]] += kinetic + potential
            self.body_total_size[when, self.model.vertex_body[i]] += kinetic + ti.abs(potential)

    @ti.func
    def limit_energy(self, x0: ti.template(), x: ti.template(), v: ti.template(), dt, accel: ti.template(),
                     keep: ti.template()):
        """Scale v - v_cm of every body whose energy rose (v_cm = 0 for pinned bodies) so that
        its kinetic energy falls by the rise. Where the rise exceeds that kinetic energy (a body
        nearly at rest in a non-convex state), the body stays where it was (x0), moving on with
        its centre's velocity when no external force could have raised it (else at rest; keep:
        its accel <- 0, the step's is not for x0). Returns how many bodies were limited."""
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_mass[b] = 0.0
            self.body_momentum_vector[b] = ti.Vector.zero(ti.f64, 3)
            self.body_kinetic[b] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
            b = self.model.vertex_body[i]
            self.body_mass[b] += m
            self.body_momentum_vector[b] += m * ti.cast(v[i], ti.f64)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):     # kinetic energy of the motion relative to the centre of mass
            b = self.model.vertex_body[i]
            m = ti.cast(self.model.mass[i] * self.model.free[i], ti.f64)
            u = ti.cast(v[i], ti.f64) - self.centre_velocity(b)
            self.body_kinetic[b] += 0.5 * m * u.norm_sqr()
        limited = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            rise = self.body_total[AFTER, b] - self.body_total[BEFORE, b]
            noise = ti.static(ROUNDOFF * epsilon()) * ti.max(self.body_total_size[BEFORE, b],
                                                               self.body_total_size[AFTER, b])
            scale = ti.cast(1.0, ti.f64)
            if rise > noise:                     # a rise within round-off is no rise
                limited += 1
                if self.body_kinetic[b] > rise:
                    scale = ti.sqrt(1.0 - rise / self.body_kinetic[b])
                else:
                    scale = -1.0                 # cannot be absorbed: keep x_n, at rest
            self.body_kinetic[b] = scale         # reused: the factor per body
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if self.body_kinetic[b] < 0.0:
                c = ti.Vector.zero(float, 3)       # gravity or the ground may have sped the centre up
                if ti.static(not (self.has_gravity or self.effects.has_ground)):
                    c = ti.cast(self.centre_velocity(b), float) * self.model.free[i]
                x[i], v[i] = x0[i] + dt * c, c
                if ti.static(keep):
                    accel[i] = ti.Vector.zero(float, 3)
            elif self.body_kinetic[b] < 1.0:
                c = self.centre_velocity(b)
                v[i] = ti.cast((c + self.body_kinetic[b] * (ti.cast(v[i], ti.f64) - c)) * self.model.free[i], float)
        return limited

    @ti.func
    def centre_velocity(self, b):
        c = ti.Vector.zero(ti.f64, 3)
        if self.body_pinned[b] == 0 and self.body_mass[b] > 0:
            c = self.body_momentum_vector[b] / self.body_mass[b]
        return c
