"""The nonlinear solve: Newton iterations on E(v) with a line search per body, or one solve.

Each Newton iteration solves H d = -grad E (fem/implicit/linear.py) to a relative accuracy FORCING (inexact
Newton; CONTACT_FORCING from the guess where contact makes no direction the answer), then every body backtracks
along its own part of d until its own E_b falls enough (Armijo): bodies never interact, so E is a sum of their
E_b, and a body hit by a violent impulse never sets the step for a quiet one. E_b is summed in float64; a body
whose decrease is below the round-off of its E_b has nothing left to gain and stops.

Convergence is tested per body: the gradient relative to the size of the step's own terms
(IncrementalPotential.gradient_norm), with a round-off floor. Only that test makes a step "converged". The
iteration also stops, unconverged, when every body's velocity stopped changing (`velocity_change`: the last
iteration moved no body's velocity by more than newton_tolerance of its size) and the gradient no longer fell
100 times (FALLING) (a stiff body's velocity settles long before its gradient meets the tolerance), when no
body can descend further at this precision, or after max_newton iterations (CONTACT_NEWTON times that with
contact); the step's stats then say it did not converge.

The step's guess for v is v_n extrapolated with the last step's change (`first_iterate`); the trapezoidal
rule, which knows a_n, blends in the extrapolated acceleration (Adams-Bashforth), each body as much as fitted
its own last step (`remember_change`). Backward Euler's first iterate is v = 0 (x = x_n), and its first Newton
iteration is the classical one-solve (stiffness-warping) step; BDF2's first iterate is the guess itself, so
its rotations are those of a position off by O(dt^3), not O(dt^2): that keeps its one-solve step second order
(docs/method.md). `one_solve` stops after the first iteration, without line search. Either starts its first
solve from the guess (`first_direction`).

Fields (n vertices, bodies of the capacity):
    velocity (n, 3)             v of the accepted iterate, m/s
    guess (n, 3)                m/s: between steps v_n - v_(n-1), the last step's change; within a
                                step v_n + scale (v_n - v_(n-1)) (+ blend_b lead), the step's guess for v
    lead (n, 3)                 m/s: the trapezoidal rule's Adams-Bashforth guess less the linear one
    blend (bodies,)             how much of `lead` body b's guess takes, in [0, 1]
    body_fit (bodies, 3)        float64 sums over a body's vertices of m miss . lead, m |lead|^2 and
                                m |miss|^2, miss the step's change less the linear guess, kg m^2/s^2
    body_E_accepted (bodies,)   E_b at the accepted iterate, J
    body_resolution (bodies,)   J: changes of E_b below this are round-off
    body_slope (bodies,)        grad_b E . d_b, J (< 0: d descends for body b)
    body_step (bodies,)         a_b: body b's step along d in the line search
    searching (bodies,)         1: body b has not found its decrease yet
    body_change (bodies,)       |a d_b|_M^2 of the last Newton iteration, J
    body_momentum (bodies,)     |v_b|_M^2, J
    body_speed_floor (bodies,)  round-off floor of |v_b|_M^2, J
"""

from dataclasses import dataclass

import taichi as ti

from fem.implicit.potential import ROUNDOFF
from fem.runtime import epsilon

ARMIJO = 1e-4            # sufficient decrease: E(v + a d) <= E(v) + ARMIJO a grad.d
MAX_HALVINGS = 12        # line search: a >= 2^-12
# A held damping frame (IncrementalPotential.holds_frame): E in the iterate's own frame may rise this many times
# what the held frame's E fell (the hard cases' E 1e9 cube: up to 2.4; cube86 stretched at nu 0.4999: 1e7)
OWN_RISE = 10.0
MAJORIZED = 6            # with contact, the first Newton iterations take friction's majorizer (`solve`)
CONTACT_NEWTON = 2       # with contact, a step may take this many times max_newton (an impact's barrier and friction)
FORCING = 0.1            # inexact Newton from v = 0: CG reduces the gradient by this factor (at least)
CONTACT_FORCING = 1e-3   # with contact, from the guess: CG reduces rho (|grad|^2) this much (docs/method.md, section 6)
FALLING = 0.01           # rho (|grad|^2) falling this much an iteration: Newton goes on past a settled velocity
FIRST_BLEND = 0.5        # a body's first blend of the Adams-Bashforth guess: v_n + dt a_n
TWO_F64 = ti.types.vector(2, ti.f64)


@dataclass
class Solved:
    """What the nonlinear solve did: rho, the weighted gradient norm at its end (<= 1: every body converged,
    the only meaning of "converged"); settled: it stopped early because every body's velocity stopped
    changing or none could descend; iterations, halvings and rotation_ms (rotation extractions) summed."""

    rho: float
    settled: bool = False
    newton_iters: int = 0
    solver_iters: int = 0
    halvings: int = 0
    rotation_ms: float = 0.0
    capped: int = 0          # Newton iterations whose linear solve stopped at max_iterations, unconverged


@ti.data_oriented
class Newton:
    """Newton's iteration for one model over the parts it drives: `potential` (E, grad E),
    `linear` (the direction), `rotations` (R at each trial), `effects` (constraints) and `sleep`."""

    def __init__(self, model, potential, linear, rotations, effects, sleep, switches):
        n, nb = model.capacity.vertices, model.capacity.bodies
        self.model, self.potential, self.linear, self.rotations = model, potential, linear, rotations
        self.effects, self.sleep = effects, sleep
        self.serial_vertices = switches.serial_vertices
        self.velocity = ti.Vector.field(3, float, n)
        self.guess = ti.Vector.field(3, float, n)
        self.lead = ti.Vector.field(3, float, n)
        self.blend = ti.field(float, nb)
        self.body_fit = ti.Vector.field(3, ti.f64, nb)
        self.body_E_accepted = ti.field(ti.f64, nb)
        self.body_resolution = ti.field(ti.f64, nb)
        self.body_slope = ti.field(ti.f64, nb)
        self.body_step = ti.field(float, nb)
        self.searching = ti.field(ti.i32, nb)
        self.body_change = ti.field(ti.f64, nb)
        self.body_momentum = ti.field(ti.f64, nb)
        self.body_speed_floor = ti.field(ti.f64, nb)
        self.from_guess = False           # the step's first iterate is its guess (else v = 0)
        self.islands, self.bend = None, None    # the solver adds Islands where contact couples bodies, and Bend

    def solve(self, cM, cK, h, tolerance, scale, settings, preconditioner, frozen=False, warm=True, bend=False):
        """Newton iterations from the first iterate until every body has converged; returns Solved.
        scale: how far the first solve extrapolates the last step's change (dt / dt_prev); frozen: the rotations
        stay those of the first iterate (the one-solve step on the ground: E is quadratic but for the ground's
        terms); warm: the first direction starts from the guess (else from 0: a solve again from an answer);
        bend: a stiff free body's trials take its turn on the arc (fem/implicit/bend.py)."""
        p = self.potential
        # With contact, friction curves by 2 / eps while a pair sticks and not at all along its slide: Newton's model
        # sends a sliding pair far past rest, and the search of every body it joins halves. The first MAJORIZED
        # directions, and each after a Newton direction that had to halve, take friction's majorizer (f1(s) / s >=
        # f1'(s) along the slide too): a quadratic above friction, whose full step never carries a pair past rest.
        # The 20-box pile, 60 steps: 14 -> 2 unconverged in f64 (6 fixed ones, a cap of 20, before); f32: islands.py
        majorized = self.effects.has_contact                  # the next direction takes the majorizer
        if majorized:
            self.effects.majorize[None] = 1
        out = Solved(rho=self.evaluate_first(h, tolerance, int(self.from_guess)))   # E and grad E: the first iterate
        # E is quadratic on linear bodies (or frozen rotations): the direction is solved to the tolerance at once (off
        # the ground one iteration is the answer); from the guess an inexact one costs a second (BDF2, epcot)
        quadratic = frozen or not self.model.any_corotational
        forcing = 0.0 if quadratic else (CONTACT_FORCING * self.effects.has_contact if self.from_guess else FORCING ** 2)
        cap = settings.max_newton * (CONTACT_NEWTON if self.effects.has_contact else 1)
        while out.rho > 1.0 and out.newton_iters < cap:
            target = max(1.0, forcing * out.rho)
            # with contact, the blocks of the pairs touching now: the step's start's made PCG's operator 40 times
            # worse conditioned once pairs came or went (two_boxes)
            rebuild = self.effects.has_contact and out.newton_iters > 0
            out.solver_iters += self.direction(cM, cK, target, warm and out.newton_iters == 0, scale, settings,
                                               preconditioner, forcing, rebuild)
            out.newton_iters, out.capped = out.newton_iters + 1, out.capped + int(self.linear.capped)
            if bend:
                self.bend.prepare(p.x0, self.velocity, self.linear.solution, h)
            largest = 1.0
            if self.effects.has_contact:                      # the pairs the search may meet; how far it may go
                largest = self.effects.contact.prepare_search(p.x, self.linear.solution, h)
            if self.start_search(tolerance, h, largest, bend) == 0:     # no body has anything left to gain
                out.settled = True
                break
            halvings, was = out.halvings, majorized
            for _ in range(MAX_HALVINGS + 1):                 # the trial iterate: each body's a_b along d
                out.rotation_ms += self.rotate(settings, frozen)
                if self.evaluate_trial(h, bend) == 0:         # E_b there; every body found its decrease
                    break
                out.halvings += 1
            else:                                             # some found no decrease at this precision
                moved = self.give_up(h, bend)                 # they keep the last iterate
                out.rotation_ms += self.rotate(settings, frozen)
                if moved == 0:
                    break
                p.energy(p.v0, p.x, p.v, h, 1)
            if self.effects.has_contact:
                majorized = out.newton_iters < MAJORIZED or (out.halvings > halvings and not was)
                self.effects.majorize[None] = int(majorized)
            change, rho = self.settle(h, tolerance, settings.newton_tolerance)
            falling, out.rho = rho < FALLING * out.rho, float(rho)
            # every body's velocity has settled and the gradient no longer falls as Newton's does; not after the
            # majorizer, whose short steps are not Newton's (two_boxes f64: 11 of 60 unconverged, 6 without)
            if change <= 1.0 and not falling and not was:
                out.settled = True
                break
        return out

    def one_solve(self, cM, cK, h, tolerance, scale, settings, preconditioner):
        """The first Newton iteration alone, with the rotations of the first iterate and no
        line search (the one-solve step); returns Solved, rho the linear solve's residual."""
        p = self.potential
        out = Solved(rho=p.gradient(p.v0, p.x, p.v, h, tolerance, True, self.from_guess))
        if out.rho > 1.0:
            out.solver_iters = self.direction(cM, cK, 1.0, True, scale, settings, preconditioner)
            out.newton_iters, out.capped = 1, int(self.linear.capped)
            out.rho = float(self.linear.rr[None])
            self.try_step(h, 0)
        return out

    def direction(self, cM, cK, target, warm, scale, settings, preconditioner, forcing=0.0, rebuild=False):
        """d <- the solution of H d = -grad E to the weighted residual `target` (forcing: inexact
        Newton's, LinearSolver.solve), from the extrapolated guess (warm) or 0, the preconditioner's
        blocks built first (rebuild); returns the linear solver's iterations."""
        return self.linear.solve(cM, cK, target, settings.max_iterations, preconditioner, self, int(warm),
                                 rebuild, forcing)

    def rotate(self, settings, frozen=False):
        """The rotations at the trial iterate (unless frozen); returns their ms."""
        p = self.potential
        if frozen or not self.model.any_corotational:       # linear tets keep R = I
            return 0.0
        ms, _ = self.rotations.update(p.x, settings.rotations == "svd", twist=True)
        return ms

    def first_iterate(self, x0, x, v, h, from_guess, v_n, scale, accel=None, dt=0.0):
        """The step's guess for v, guess <- v_n + scale (v_n - v_(n-1)): the velocity extrapolated with
        the last step's change (scaled by the ratio of the dts; on a turning body it takes a quarter to
        a third of PCG's first iterations off, docs/method.md, section 7). Then the first Newton
        iterate: v = the guess (from_guess) or 0, x = x^ + h v; x holds x_n. Given the trapezoidal
        rule's a_n (`accel`, at the same dt), v_n + dt (3 a_n - a_(n-1)) / 2, the Adams-Bashforth
        guess, is one order closer where the motion is resolved (a_(n-1) = 2 (v_n - v_(n-1)) / dt -
        a_n, the rule's own update), but the rule keeps the fast modes a step does not resolve ringing
        in a_n, and there it is further off. So each body's guess goes `blend_b` of the way from the
        linear guess to it, blend_b fitted to its last step (`remember_change`). Newton iterations a
        step at dt 0.02 s: torsion 1.57 -> 1.09, box1k 1.94 -> 1.24, epcot 1.88 -> 1.62, fertility
        1.24 -> 1.26 (the Adams-Bashforth guess alone: 2.19, and a body coming to rest in f32 kept
        jittering above its sleep threshold). A vertex pressed into the ground starts at v = 0 either
        way: friction's curvature is that of sticking there, and a faster guess would start it sliding."""
        self.from_guess = bool(from_guess)                    # v != 0: its damping terms count
        known = accel is not None
        self.start_iterate(x0, x, v, h, int(from_guess), v_n, scale, accel if known else v_n, int(known), dt)

    @ti.kernel
    def start_iterate(self, x0: ti.template(), x: ti.template(), v: ti.template(), h: float,
                      from_guess: ti.i32, v_n: ti.template(), scale: float, accel: ti.template(),
                      known: ti.i32, dt: float):
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            b = self.model.vertex_body[i]
            change = self.guess[i]                            # v_n - v_(n-1)
            lead = ti.Vector.zero(float, 3)
            if known and self.sleep.awake[b]:
                lead = 2.0 * (dt * accel[i] - change)         # dt (3 a_n - a_(n-1)) / 2 less the change
            self.lead[i] = lead
            self.guess[i] = v_n[i] + scale * (change + self.blend[b] * lead)
            u = ti.Vector.zero(float, 3)
            if from_guess and not self.effects.pressed(x[i]):
                u = self.effects.filtered(i, self.guess[i])
            self.velocity[i] = u
            v[i] = u
            x[i] = x0[i] + h * u

    @ti.kernel
    def forget_change(self):
        """The last step's velocity change <- 0, and every body's blend its first."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.guess[i] = ti.Vector.zero(float, 3)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.blend[b] = FIRST_BLEND

    @ti.func
    def remember_change(self, v_n, v, good, fit):
        """guess <- the step's change v - v_n, the next step's (0 after a step whose result is not
        finite); after a step that had a lead (fit: the trapezoidal rule's), each body's blend <- the
        share of its lead that would have guessed this step's change best (least squares in the mass
        norm, clipped to [0, 1]; kept where it had none)."""
        self.sleep.sums.reduce(self.fit, self.store_fit, (v_n, v, good, fit))
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None] * fit):
            along, lead, missed = self.body_fit[b][0], self.body_fit[b][1], self.body_fit[b][2]
            if lead > 0 and missed > 0:
                # the best share, times the share of the miss it explains (cos^2 of their angle):
                # a lead that is noise (a body coming to rest, in f32) explains little and adds little
                share = ti.min(ti.max(along / lead, 0.0), 1.0)
                self.blend[b] = ti.cast(share * ti.min(along * along / (lead * missed), 1.0), float)

    @ti.func
    def fit(self, i, b, data: ti.template()):
        """guess[i] <- vertex i's change; returns m (missed . lead, |lead|^2, |missed|^2) for `remember_change`."""
        v_n, v = ti.static(data[0], data[1])
        good, fit = data[2], data[3]
        change = ti.Vector.zero(float, 3)
        out = ti.Vector.zero(ti.f64, 10)
        if good:
            change = v[i] - v_n[i]
        if good and fit:
            missed = v[i] - self.guess[i] + self.blend[b] * self.lead[i]   # the change less the linear guess
            m = ti.cast(self.model.mass[i], ti.f64)
            out[0] = m * ti.cast(missed.dot(self.lead[i]), ti.f64)
            out[1] = m * ti.cast(self.lead[i].norm_sqr(), ti.f64)
            out[2] = m * ti.cast(missed.norm_sqr(), ti.f64)
        self.guess[i] = change
        return out

    @ti.func
    def store_fit(self, b, total, data: ti.template()):
        self.body_fit[b] = ti.Vector([total[0], total[1], total[2]])

    @ti.func
    def slope(self, i, b, data: ti.template()):
        """Vertex i's share of its body's slope grad E . d."""
        s = -self.effects.filtered(i, self.potential.rhs[i]).dot(self.linear.solution[i])
        return ti.Vector([ti.cast(s, ti.f64), 0, 0, 0, 0, 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_slope(self, b, total, data: ti.template()):
        self.body_slope[b] = total[0]

    @ti.func
    def change(self, i, b, data: ti.template()):
        """Vertex i's (|a_b d_i|_m^2, |v_i|_m^2) for `velocity_change`."""
        m = ti.cast(self.model.mass[i], ti.f64)
        return ti.Vector([m * ti.cast(self.body_step[b] * self.linear.solution[i], ti.f64).norm_sqr(),
                          m * ti.cast(self.velocity[i], ti.f64).norm_sqr(), 0, 0, 0, 0, 0, 0, 0, 0], ti.f64)

    @ti.func
    def store_change(self, b, total, data: ti.template()):
        self.body_change[b], self.body_momentum[b] = total[0], total[1]

    @ti.func
    def first_direction(self, warm):
        """The linear solve's first guess: d <- the guess less the iterate (filtered), or 0."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            d = ti.Vector.zero(float, 3)
            if warm:
                d = self.effects.filtered(i, self.guess[i] - self.velocity[i])
            self.linear.solution[i] = d

    @ti.kernel
    def start_search(self, tolerance: ti.f64, h: float, largest: float, bend: ti.template()) -> ti.i32:
        """body_slope[b] <- grad_b E . d_b (J, < 0 where d descends). A body whose decrease
        -slope_b is above the round-off of its E_b, or whose gradient has not met the tolerance,
        searches, from a_b = largest (1, or less where contact bounds the step); the others have
        nothing left to gain (a_b = 0). Returns how many
        bodies search. (Near the answer E changes by |grad|^2 / H: in f32 below E's round-off
        from a gradient of about 1e-4 on, where only the gradient still tells how close it is.)"""
        self.sleep.sums.reduce(self.slope, self.store_slope, 0)
        count = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            unconverged = self.potential.body_gradient[b] > (tolerance * tolerance * self.potential.body_scale[b]
                                                             + self.potential.body_floor[b] + self.effects.round_off(b))
            self.searching[b] = int(self.body_slope[b] < 0 and (-self.body_slope[b] > self.body_resolution[b]
                                                               or unconverged))
            self.body_step[b] = self.searching[b] * largest
            count += self.searching[b]
        if ti.static(self.effects.has_contact):               # contact couples the bodies' energies
            count = self.islands.search_together(tolerance)
        self.step_along(h, 1, int(count > 0), bend)           # the first trial
        return count

    # ------------------------------------------------------------ the iterates' kernels: one launch each

    @ti.kernel
    def evaluate_first(self, h: float, tolerance: ti.f64, moving: ti.i32) -> ti.f64:
        """E_b and -grad E at the first iterate (moving=0: v = 0), which becomes the accepted
        one; returns the gradient's weighted norm rho (converged: rho <= 1)."""
        self.potential.iterate_energy(h, moving)              # with the tet terms of grad E
        rho = self.potential.iterate_gradient(h, tolerance, 1, moving)
        self.accept(1)
        return rho

    @ti.kernel
    def evaluate_trial(self, h: float, bend: ti.template()) -> ti.i32:
        """E_b at the trial iterate, then `armijo`, then the next trial (a body done keeps its
        a_b, and its iterate: the same numbers); returns how many bodies still search."""
        self.potential.iterate_energy(h, 1)
        left = 0
        if ti.static(self.effects.has_contact):               # contact couples the bodies' energies
            left = self.islands.armijo(h)
        else:
            left = self.armijo()
        self.step_along(h, 1, int(left > 0), bend)            # none left: x, v stay the accepted trial
        return left

    @ti.kernel
    def settle(self, h: float, tolerance: ti.f64, newton_tolerance: ti.f64) -> TWO_F64:
        """The trial becomes the accepted iterate; returns (`velocity_change`, rho there: the energy pass's terms)."""
        self.accept(0)
        change = self.velocity_change(newton_tolerance)
        rho = self.potential.iterate_gradient(h, tolerance, 0, 1)
        return ti.Vector([change, rho], ti.f64)

    @ti.func
    def armijo(self):
        """A body whose E_b fell by ARMIJO a_b |slope_b| is done, the others halve a_b; returns how many go on."""
        left = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.searching[b]:
                # a change within E_b's round-off is noise: without that slack the search would end at a
                # gradient of sqrt(epsilon), 3e-4 in f32, where E can no longer tell better from worse
                E_b, accepted = self.potential.body_E[b], self.body_E_accepted[b]
                descent = E_b <= accepted + ARMIJO * self.body_step[b] * self.body_slope[b] + self.body_resolution[b]
                if ti.static(self.potential.holds_frame):   # the held frame's E is the gradient's model; E in
                    own = E_b + self.potential.body_shift[b]  # the iterate's own frame is kept from running off
                    descent = descent and own - accepted <= OWN_RISE * (accepted - E_b) + self.body_resolution[b]
                if descent:
                    self.searching[b] = 0
                else:
                    self.body_step[b] *= 0.5
                    left += 1
        return left

    @ti.kernel
    def give_up(self, h: float, bend: ti.template()) -> ti.i32:
        """Bodies that found no decrease (at this precision) stay where they are: a_b = 0, and
        the trial iterate with those steps. Returns how many bodies still move."""
        moving = 0
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            if self.searching[b]:
                self.body_step[b] = 0.0
            moving += int(self.body_step[b] > 0)
        self.step_along(h, 1, 1, bend)
        return moving

    @ti.kernel
    def try_step(self, h: float, each: ti.i32):
        """`step_along`: the iterate v <- velocity + a d, x <- x^ + h v."""
        self.step_along(h, each, 1, False)

    @ti.func
    def step_along(self, h, each, on, bend: ti.template()):
        """v <- velocity + a d, x <- x^ + h v: a point on the Newton direction (bend: on a stiff body's
        arc), a = 1 for every body, or (each = 1) each body's own a_b. on = 0: the loop runs over nothing."""
        x0, x, v = ti.static(self.potential.x0, self.potential.x, self.potential.v)
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None] * on):
            a = 1.0
            if each:
                a = self.body_step[self.model.vertex_body[i]]
            u = self.velocity[i] + a * self.linear.solution[i]
            if ti.static(bend):                               # a stiff body's turn on its arc (bend.py)
                u += self.bend.correction(i, x0, self.velocity, a, h)
            v[i] = u
            x[i] = x0[i] + h * u

    @ti.func
    def accept(self, first):
        """The iterate v (and its energies E_b) becomes the accepted one; on the step's first
        iterate E_b also sets its resolution, the round-off of a float64 sum of that size."""
        v = ti.static(self.potential.v)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_E_accepted[b] = self.potential.body_E[b]
            if ti.static(self.potential.holds_frame):         # E_b in its own damping frame: the next search's
                self.body_E_accepted[b] += self.potential.body_shift[b]
            if first:
                self.body_resolution[b] = ti.static(ROUNDOFF * epsilon()) * ti.abs(self.potential.body_E[b])
        if ti.static(self.potential.holds_frame):             # the next line search's damping frame
            ti.loop_config(serialize=self.potential.serial_tets)
            for e in range(self.model.tet_count[None]):
                self.potential.held_Bm[e] = self.rotations.rotated_Bm[e]
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.velocity[i] = v[i]

    @ti.func
    def velocity_change(self, tolerance):
        """sum_b |a_b d_b|_M^2 / (tol^2 |v_b|_M^2 + floor_b): <= 1 exactly when no body's velocity
        moved by more than tol of its size (or by round-off) in the last Newton iteration."""
        self.sleep.sums.reduce(self.change, self.store_change, 0)
        change = ti.cast(0.0, ti.f64)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            floor = self.body_speed_floor[b] * self.potential.body_far[b]     # eps D / h, D >= L (potential.py)
            change += self.body_change[b] / (tolerance * tolerance * self.body_momentum[b] + floor)
        return change
