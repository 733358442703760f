"""What the step promises whatever the solve did: finite results, exact momentum, no energy gain.

- `check_finite`: a step whose result is not finite is rejected (the caller keeps its state).
- `restore_momentum`: an inexact solve leaves a residual whose sum is not zero, and internal
  forces can never change momentum: each unpinned body's velocity is shifted uniformly so
  that its momentum is exactly the integrator's (bodies the ground does not touch).
- `limit_energy`, the energy projection (docs/method.md, section 6): each body is brought onto
  its energy target by the smallest correction that keeps its momentum, centre and angular
  momentum: its deformation velocities (what is left of v once its centre's velocity and rigid
  spin omega x r are taken out) scaled, and where that cannot pay, its deformation's positions
  moved first (`InternalMove`, fem/implicit/projection.py). For the conserving
  scheme (the undamped trapezoidal rule off the ground) the target is the energy the body
  began with, both ways, and its spin is reset to the angular momentum it began with; for
  every other Newton step only a rise is taken out. A rise within round-off is no rise, and
  round-off is measured against the body's own history (`start_band`): its energy may wander
  up to ROUNDOFF eps of the largest size its terms have had since the last change from
  outside above the lowest energy it has had since then, and no further.
- `fall_back` (fem/implicit/fallback.py): a rise the projection cannot pay for, beyond the error the
  solve's tolerance allows (a failed solve), is trimmed: the body takes a rigid step from its start
  instead, and goes on moving. StepInfo counts these trims.

Fields (bodies of the capacity; energies summed in float64):
    body_total (2, bodies)       each body's total energy [BEFORE, AFTER] the step, J
    body_total_size (2, bodies)  the sum of the sizes of its terms, J: the scale of its round-off
    body_mass (bodies,)          kg (free vertices only, for the energy limit)
    body_momentum_vector (bodies, 3)   kg m/s
    body_kinetic (bodies,)       J: kinetic energy relative to the centre of mass
    body_deformation (bodies,)   J: the kinetic energy of its deformation, then the factor
                                 the deformation's velocities are scaled by (1 - lam)
    body_centre (bodies, 3)      m: its centre of mass
    body_spin (bodies, 3)        its angular momentum about the centre (kg m^2/s), then omega (1/s)
    body_inertia (bodies, 3x3)   its inertia tensor about the centre, kg m^2 (a rigid step: its turn)
    body_arc (bodies, 3x3)       its rigid turn over the step (`arc_first_iterate`)
    body_arc_centre (bodies, 4)  m: its centre at the step's first iterate, and its vertices pressed
                                 into the ground at x_n (`arc_first_iterate`)
    body_pinned (bodies,)        1: the body has pinned vertices
    body_lowest (bodies,)        J: the lowest total energy it has had since the band started
    body_scale (bodies,)         J: the largest sum of its terms' sizes since then (-1: no band yet)
    body_elastic (bodies,)       its elastic energy when last summed, J: a step that starts where
                                 the last one ended (the same positions and rotations) reuses it
    body_spin_before (bodies, 3) its angular momentum about its centre BEFORE the step, kg m^2/s
    body_spin_new (bodies, 3)    1/s: the spin it ends with (the conserving scheme: I^-1 L_n)
    body_shift_vector (bodies, 3)  m: a rigid step's move of the centre
    body_fallback (bodies,)      1: trimmed this step (`fall_back`)
    body_failed (bodies,)        1: its solve failed this step, a rise beyond round-off (`strained`)
    body_touching (bodies,)      1: pressed into the ground at the step's start or end (`find_contacts`)
    body_speed (bodies,)         a trimmed body's velocity factor on the ground (`slowed`)
    body_kinetic_before (bodies,)  J: its kinetic energy BEFORE the step
    body_elastic_before (bodies,)  J: its elastic energy BEFORE the step (`strained`)
    body_stiffness (bodies,)     J: sum of mu V over its tets (`strained`)
    body_moving (bodies,)        J: its kinetic energy (`rigid_motion`)
    body_quiet (bodies,)         J: the energy round-off gives a body at rest, where the sizes of its
                                 terms are 0 (`Model.body_quiet`): a rise below it is no failed solve
"""

from dataclasses import dataclass

import taichi as ti

from fem.elastic import is_finite
from fem.implicit.potential import ROUNDOFF
from fem.implicit.fallback import AFTER, BEFORE, Fallback   # noqa: F401 (BEFORE, AFTER: the solver's too)
from fem.implicit.projection import FAILED, PENDING, InternalMove
from fem.runtime import epsilon

# The conserving projection gives energy back only where that scales a body's deformation
# velocities up by at most this share: energy the step lost in a mode it cannot follow (a
# stiff body's unresolved breathing) is not pumped into another
LIFT = 0.1
FIVE_I32 = ti.types.vector(5, ti.i32)


@dataclass(frozen=True)
class Ending:
    """What a step's end is checked for (`Safeguards.end_step`): newton, a Newton step (its
    energy measured and projected); keep, the history keeps the step's acceleration a_(n+1) (a
    one-step rule); conserve, the conserving scheme (onto the energy BEFORE, both ways);
    solved, the solve's result is finite; tolerance, the one every body's solve met (0: some
    body's did not)."""

    newton: bool
    keep: int
    conserve: int
    solved: bool
    tolerance: float


@dataclass(frozen=True)
class Ended:
    """What the step's end did: finite, every new position and velocity is (else the caller
    keeps its state); trimmed, bodies whose rise the projection could not pay for; rigid, of those
    the bodies that took a rigid step; strained, of those the ones that began the step strained
    (the next step is backward Euler's); rotation_ms, time in rotation extraction."""

    finite: bool
    trimmed: int
    rigid: int
    strained: int
    rotation_ms: float


@ti.data_oriented
class Safeguards(Fallback, InternalMove):
    """The step's last checks for one model, on the iterate of `potential`: energies from
    `elasticity` and `effects` (gravity), a sleeping body (`sleep`) left as it is; the
    trapezoidal rule's a_(n+1) into `history`."""

    def __init__(self, model, potential, history, elasticity, effects, sleep, switches):
        nb = model.capacity.bodies
        self.model, self.elasticity, self.effects, self.sleep = model, elasticity, effects, sleep
        self.potential, self.history = potential, history         # the iterate; a_(n+1)
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
        self.body_arc = ti.Matrix.field(3, 3, ti.f64, nb)
        self.body_arc_centre = ti.Vector.field(4, ti.f64, nb)
        self.body_pinned = ti.field(ti.i32, nb)
        self.body_lowest = ti.field(ti.f64, nb)
        self.body_scale = ti.field(ti.f64, nb)
        self.body_elastic = ti.field(ti.f64, nb)
        self.body_spin_before = ti.Vector.field(3, ti.f64, nb)
        self.body_fallback = ti.field(ti.i32, nb)
        self.body_failed = ti.field(ti.i32, nb)
        self.body_touching = ti.field(ti.i32, nb)
        self.body_spin_new = ti.Vector.field(3, ti.f64, nb)
        self.body_shift_vector = ti.Vector.field(3, ti.f64, nb)
        self.body_speed = ti.field(ti.f64, nb)
        self.body_moving = ti.field(ti.f64, nb)
        self.body_kinetic_before = ti.field(ti.f64, nb)
        self.body_elastic_before = ti.field(ti.f64, nb)
        self.body_stiffness = ti.field(ti.f64, nb)
        self.body_quiet = ti.field(ti.f64, nb)
        self.make_move_fields(nb, model.capacity.vertices)
        self.forget_band()

    def forget_band(self):
        """The next step starts every body's band anew (a new state: `start_band`)."""
        self.body_scale.fill(-1.0)

    def end_step(self, start, h, dt, ending, rotations_at):
        """The step's end, entered once from the step (`ImplicitSolver.step`): finite, momentum and
        energy on the iterate (`after_step`); where a rise is more than the velocities can pay, the
        positions move first (`move_positions`); a body trimmed all the same takes a rigid step
        (`fall_back`), which `settle` measures again. start: the step's State (x_n, v_n); ending:
        an Ending; rotations_at(x) extracts the rotations at x and returns its ms. Returns an Ended."""
        x, v = self.potential.x, self.potential.v
        self.solve_tolerance[None] = ending.tolerance     # its band (`solve_band`), for bodies that cannot move
        bad, trimmed, rigid, strained, pending = self.after_step(start, h, dt, ending.newton, ending.keep,
                                                                 ending.conserve)
        finite, ms = bad == 0 and ending.solved, 0.0
        if finite and pending > 0:            # a rise the velocities cannot pay: positions pay first
            trimmed, rigid, strained, ms = self.move_positions(start, dt, ending.conserve, ending.tolerance,
                                                               rotations_at)
        if finite and rigid > 0 and not self.effects.has_contact:   # a rigid step's rounding strains a stiff body in f32
            ms += rotations_at(x)
            self.settle(start.x, x, v)
        return Ended(finite, int(trimmed) if finite else 0, int(rigid), int(strained), ms)

    @ti.kernel
    def after_step(self, start: ti.template(), h: float, dt: float, energy: ti.template(), keep: ti.i32,
                   conserve: ti.i32) -> FIVE_I32:
        """The step's last checks on the potential's iterate x, v, in one launch, from the step's
        start (`start`: a State, x_n and v_n); returns (vertices not finite, bodies trimmed,
        bodies that took a rigid step: the same, of those the `strained`). Without contact each
        body's momentum is `restore_momentum`'s; energy (a Newton step): the total energy AFTER
        and `limit_energy` (conserve: to the energy BEFORE, both ways). keep: the history's
        a_(n+1) <- the step's acceleration (v - v^) / h, what the forces did, before the energy
        projection corrects anything (the trapezoidal rule's, fem/implicit/integrators.py). The
        caller discards a result that is not finite, whatever these did with it."""
        x0, v0, x, v = ti.static(self.potential.x0, self.potential.v0, self.potential.x, self.potential.v)
        bad = self.check_finite(x, v)
        self.find_contacts(start.x, x)
        if ti.static(not self.effects.has_contact):       # contact's pushes are no internal forces
            self.restore_momentum(v0, x0, x, v, h)
            if ti.static(self.effects.has_ground):     # a restored body moved: it may end in the ground now
                self.find_contacts(start.x, x)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if keep:
                self.history.accel[i] = (v[i] - v0[i]) / h
        counts = ti.Vector([0, 0, 0], ti.i32)
        strained = 0
        if ti.static(energy):
            self.total_energy(x, v, AFTER, 1)
            self.sleep.fastest.reduce(self.lightest, self.solve_band, x)
            counts = self.limit_energy(x, v, conserve, 0)
            if counts[1] > 0 and counts[2] == 0:     # else after the move (`InternalMove.after_move`)
                strained = self.strained()
                self.fall_back(start.x, start.v, x, v, dt)
        return ti.Vector([bad, counts[0], counts[1], strained, counts[2]], ti.i32)

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
    def find_contacts(self, x_n: ti.template(), x: ti.template()):
        """body_touching[b] <- 1 where some vertex of body b is pressed into the ground at the
        step's start or end: the ground may have pushed it, so its momentum is not internal
        forces' and gravity's alone. (No ground: every body is free.)"""
        if ti.static(self.effects.has_ground):
            self.sleep.fastest.reduce(self.ground_contact, self.store_contact, (x_n, x))
        else:
            ti.loop_config(serialize=True)
            for b in range(self.model.body_count[None]):
                self.body_touching[b] = 0

    @ti.func
    def ground_contact(self, i, b, data: ti.template()):
        """Vertex i's (1 if pressed into the ground at the step's start or end else 0, 0), for
        `find_contacts`' largest."""
        x_n, x = ti.static(data[0], data[1])
        pressed = ti.cast(self.effects.pressed(x_n[i]) or self.effects.pressed(x[i]), ti.f64)
        return ti.Vector([pressed, 0.0], ti.f64)

    @ti.func
    def store_contact(self, b, largest, data: ti.template()):
        self.body_touching[b] = ti.cast(largest[0] > 0.5, ti.i32)

    @ti.func
    def restore_momentum(self, v0: ti.template(), x0: ti.template(), x: ti.template(), v: ti.template(), dt):
        """Shift each unpinned body's velocity uniformly so that its momentum is exactly backward
        Euler's, (1 + dt alpha) sum m v = sum m v^ + dt M g."""
        self.sleep.sums.reduce(self.momentum_missing, self.store_momentum, (v0, v, dt))
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            if self.body_pinned[b] == 0 and self.body_touching[b] == 0 and self.body_mass[b] > 0 and self.sleep.awake[b]:
                u = ti.cast(self.body_momentum_vector[b] / self.body_mass[b], float)
                v[i] += u
                x[i] = x0[i] + dt * v[i]

    @ti.func
    def momentum_missing(self, i, b, data: ti.template()):
        """Vertex i's (mass, momentum backward Euler gives it - its momentum) for `restore_momentum`."""
        v0, v = ti.static(data[0], data[1])
        dt = data[2]
        m = ti.cast(self.model.mass[i], ti.f64)
        g = ti.Vector.zero(ti.f64, 3)
        if ti.static(self.has_gravity):
            g = dt * ti.cast(self.effects.gravity_vector(), ti.f64)
        p = m * ((ti.cast(v0[i], ti.f64) + g) / (1.0 + dt * self.effects.mass_damping[None]) - ti.cast(v[i], ti.f64))
        return ti.Vector([m, p[0], p[1], p[2], 0, 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_momentum(self, b, total, data: ti.template()):
        self.body_mass[b] = total[0]
        self.body_momentum_vector[b] = ti.Vector([total[1], total[2], total[3]])

    @ti.kernel
    def body_energy(self, x: ti.template(), v: ti.template(), when: ti.template(), tets: ti.i32):
        """`total_energy` (tets=0: the elastic energies of the last sum, for the same x and R);
        BEFORE a step, `start_band` too."""
        self.total_energy(x, v, when, tets)
        if ti.static(when == BEFORE):
            self.start_band()
            self.rigid_motion(x, v)
            ti.loop_config(serialize=True)
            for b in range(self.model.body_count[None]):     # L about the centre: the conserving target
                self.body_spin_before[b] = self.body_inertia[b] @ self.body_spin[b]
                self.body_kinetic_before[b] = self.body_moving[b]
                self.body_elastic_before[b] = self.body_elastic[b]
            if ti.static(self.effects.has_contact):          # one island: body 0's entry holds the sum
                ti.loop_config(serialize=True)
                for b in range(1, self.model.body_count[None]):
                    self.body_kinetic_before[0] += self.body_kinetic_before[b]

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
        self.sleep.tet_sums.reduce(self.tet_elastic, self.store_elastic, x, tets)   # over each body's tets
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_total[when, b], self.body_total_size[when, b] = 0.0, 0.0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_total[when, self.island(b)] += self.body_elastic[b]
            self.body_total_size[when, self.island(b)] += self.body_elastic[b]
        if ti.static(self.effects.has_contact):
            self.effects.contact.share_energy(x)
        self.sleep.sums.reduce(self.vertex_energy, self.store_energy, (x, v, when))

    @ti.func
    def tet_elastic(self, e, b, x: ti.template()):
        return ti.Vector([self.elasticity.elastic_energy(x, e)], ti.f64)

    @ti.func
    def store_elastic(self, b, total, x: ti.template()):
        self.body_elastic[b] = total[0]

    @ti.func
    def vertex_energy(self, i, b, data: ti.template()):
        """Vertex i's (kinetic + gravitational + stored contact energy, the sum of their sizes), J."""
        x, v = ti.static(data[0], data[1])
        m = ti.cast(self.model.mass[i], ti.f64)
        kinetic, potential = 0.5 * m * ti.cast(v[i], ti.f64).norm_sqr(), ti.cast(0.0, ti.f64)
        if ti.static(self.has_gravity):
            potential = -m * ti.cast(self.effects.gravity_vector(), ti.f64).dot(ti.cast(x[i], ti.f64))
        if ti.static(self.effects.has_ground):
            kinetic += self.effects.contact_energy(i, x[i])      # stored in the ground's penalty
        if ti.static(self.effects.has_contact):
            kinetic += self.effects.contact.energy[i]             # its share of the pairs' penalty
        return ti.Vector([kinetic + potential, kinetic + ti.abs(potential), 0, 0, 0, 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_energy(self, b, total, data: ti.template()):
        when = data[2]
        self.body_total[when, self.island(b)] += total[0]        # several bodies may share an island
        self.body_total_size[when, self.island(b)] += total[1]

    @ti.func
    def limit_energy(self, x: ti.template(), v: ti.template(), conserve, final):
        """Bring each body's energy to its target by the smallest correction that keeps its
        momentum, its centre and its angular momentum (module docstring, "The energy projection").
        conserve=1 (the conserving scheme): the target is the energy BEFORE the step, both ways,
        and an unpinned body's spin is set to the angular momentum it began with,
        omega' = I^-1 L_n; else only a rise above the band is taken out, to the band's middle,
        and the spin stays. Then its deformation velocities w = v - v_c - omega x r are scaled by
        1 - lam, lam the smaller root of the exact change (lam^2 - 2 lam) K_w = -excess. A rise
        more than that can take is, on a free body off the ground (final=0), left for
        `InternalMove` (fem/implicit/projection.py): its positions' deformation pays for it, and
        this is done again at the moved positions (final=1). Where even then the rise is more
        than the scale can take (a failed solve: its deformation cannot pay for it) the body is
        trimmed: where the scheme keeps no angular momentum (conserve=0) its spin pays too,
        scaled by 1 - lam with w (a converged BDF2 step of a spinning box, whose deformation
        holds 1e-3 of its energy, rose by more than that); only a rise beyond that is a failed
        solve and `fall_back`. Returns (bodies trimmed, bodies to `fall_back`, bodies left for
        the move): the projection itself is part of the scheme and is not counted, nor is a body
        whose rise is round-off at rest (`body_quiet`), which takes the rigid step, and so stays
        still, with no failed solve to count."""
        self.rigid_motion(x, v)
        trimmed, falls, pending = 0, 0, 0
        if ti.static(self.effects.has_contact):                # one island: body 0's entries hold the sums
            ti.loop_config(serialize=True)
            for b in range(1, self.model.body_count[None]):
                self.body_deformation[0] += self.body_deformation[b]
                self.body_moving[0] += self.body_moving[b]
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            energy, allowance = self.body_total[AFTER, b], self.allowance(b, self.body_total_size[AFTER, b])
            omega = self.body_spin[b]
            self.body_spin_new[b] = omega
            excess = ti.cast(0.0, ti.f64)
            if conserve:
                excess = energy - self.body_total[BEFORE, b]
                I = self.body_inertia[b]
                if self.keeps_spin(b):      # (linear FEM's forces turn a body: no invariant L there)
                    spun = I.inverse() @ self.body_spin_before[b]
                    excess += 0.5 * (spun.dot(I @ spun) - omega.dot(I @ omega))
                    self.body_spin_new[b] = spun
            else:                           # a rise within round-off is no rise
                gained = energy + self.spin_by_law(b, energy - self.body_lowest[b] - 0.5 * allowance)
                if gained > self.body_lowest[b] + allowance:
                    excess = gained - self.body_lowest[b] - 0.5 * allowance
            K = self.body_deformation[b]
            # a scheme that keeps no angular momentum (BDF2, damping, the ground) may take a rise
            # its deformation cannot pay for out of its spin too: v - v_c scaled whole
            spin = ti.cast(0.0, ti.f64)
            if ti.static(not self.effects.has_contact):
                if not conserve and excess > FAILED * K:
                    spin = 0.5 * omega.dot(self.body_inertia[b] @ omega)
            lam = ti.cast(0.0, ti.f64)
            self.body_fallback[b], self.body_failed[b] = 0, 0
            paid = excess
            # a rise within what the solve's tolerance leaves (`solve_band`) is no failed solve, on a body
            # whose positions may not pay (two_boxes falling, f64: 4e-10 to 9e-8 J, a band of 2e-6 to 2e-5)
            band = self.band(b, K, conserve, excess - allowance)
            within = excess > FAILED * (K + spin) and excess <= allowance + band
            if within and (final or not self.movable(b)):
                paid = FAILED * (K + spin)             # the rest is the solve's own error (`solve_band`)
            elif excess > FAILED * (K + spin) and excess > allowance and final == 0 and self.movable(b):
                self.body_fallback[b] = PENDING        # its positions pay first (`InternalMove`)
                self.body_spin_new[b] = omega
                self.body_move[b] = ti.Vector([excess, K + spin, 0.0, 0.0], ti.f64)
                pending += 1
            elif excess > FAILED * (K + spin) and excess > allowance:
                self.body_fallback[b] = 1
                falls += 1
                # a body at rest (no gravity: terms of size 0) whose energy rose by round-off
                # takes the rigid step too, which keeps it still, but no solve failed there
                if excess > allowance + self.body_quiet[b] * self.potential.body_far[b]:
                    trimmed, self.body_failed[b] = trimmed + 1, 1
                self.body_speed[b] = self.slowed(b, energy)
            if self.body_fallback[b] == 0 and K + spin > 0.0 and ti.abs(excess) > allowance:   # round-off is not chased
                # the smaller root, in the form that does not cancel
                W = K + spin
                lam = 2.0 * paid / (2.0 * W + ti.sqrt(ti.max(4.0 * W * W - 4.0 * W * paid, 0.0)))
                if lam < -LIFT:             # energy the step lost comes back only by a small correction
                    lam = 0.0
                if spin > 0.0:
                    self.body_spin_new[b] = (1.0 - lam) * omega
            self.body_total[AFTER, b] = energy + 0.5 * (self.body_spin_new[b].dot(self.body_inertia[b] @ self.body_spin_new[b])
                                                        - omega.dot(self.body_inertia[b] @ omega)) \
                + (lam * lam - 2.0 * lam) * K
            if self.body_fallback[b] == 1:
                self.body_total[AFTER, b] = self.body_total[BEFORE, b]     # at most: `fall_back`
            self.body_deformation[b] = 1.0 - lam          # reused: the factor
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b, f = self.model.vertex_body[i], self.island(self.model.vertex_body[i])    # f: whose factors
            if self.body_deformation[f] != 1.0 or (self.body_spin_new[b] != self.body_spin[b]).any():
                c = self.centre_velocity(b)
                r = ti.cast(x[i], ti.f64) - self.body_centre[b]
                w = ti.cast(v[i], ti.f64) - c - self.body_spin[b].cross(r)
                u = c + self.body_spin_new[b].cross(r) + self.body_deformation[f] * w
                v[i] = ti.cast(u * self.model.free[i], float)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):       # the band follows the corrected energy
            self.body_lowest[b] = ti.min(self.body_lowest[b], self.body_total[AFTER, b])
        return ti.Vector([trimmed, falls, pending], ti.i32)
