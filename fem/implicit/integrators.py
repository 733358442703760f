"""The integrators: what each one puts into the incremental potential (fem/implicit/potential.py).

For this solver an implicit integrator is an inertia target (x^, v^) and an effective step h:
the step's velocity v minimises E(v) built from them, and x_(n+1) = x^ + h v.

    backward-euler   x^ = x_n,                     v^ = v_n,                     h = dt
    bdf2             x^ = (4 x_n - x_(n-1)) / 3,   v^ = (4 v_n - v_(n-1)) / 3,   h = 2 dt / 3
    trapezoidal      x^ = x_n + h v_n,             v^ = v_n + h a_n,             h = dt / 2

Backward Euler is first order: its error is a damping of every motion, of order omega^2 dt
per second for a mode of frequency omega, and it dominates what a spinning or wobbling body
loses. BDF2 (the two-step backward differentiation formula) is second order and damps only
at order omega^4 dt^3. The trapezoidal rule (Newmark's average acceleration) is second
order with a smaller error (about a third of BDF2's on a spinning body) and damps nothing:
x_(n+1) = x_n + dt (v_n + v_(n+1)) / 2, v_(n+1) = v_n + dt (a_n + a_(n+1)) / 2, where a_n,
the acceleration at the end of the last step (every force: elastic, gravity, damping,
contact), is read off that step's own update, a_n = (v_n - v^) / h, before the energy
projection (fem/implicit/safeguards.py) corrects anything. On the non-convex corotated energy it
keeps neither energy nor angular momentum by itself; undamped and off the ground, that
projection puts each body back on both every step: the conserving scheme. `theta_rule(rho)`
generalises it with numerical dissipation (SolverSettings.rho_infinity).

The trapezoidal rule is a one-step scheme: after anything that breaks the history (the first
step, an impulse, a new state, a live edit, a change of dt or of integrator, a rejected step)
its a_n is the acceleration the forces give at the step's start (`History.fresh`; the solver
computes it). BDF2 needs the previous step: after a break its x_(n-1), v_(n-1) are read off
x_n, v_n and that same a_n (`History.extrapolate`), so that an undamped second-order run never
takes a first-order step (a backward Euler start cost a falling body 0.5 g dt^2 and a spinning
one 2 % of its energy); a damped one starts with a backward Euler step (below). Sleeping bodies
keep their place exactly.

"auto", the default, is the trapezoidal rule, but BDF2 in a scene with a ground or contact
(`chosen`): the ground's penalty is far stiffer than any body (fem/implicit/effects.py), and the
trapezoidal rule, which damps nothing, lets it ring; on the bunny resting on the ground its Newton
step took 5.4 iterations a step to BDF2's 2.5, and its error did not fall with dt
(docs/benchmark.md). Rayleigh damping overdamps the fast modes, which the trapezoidal rule keeps
ringing too (times -rho_infinity a step): the coursework's struck linear epcot reached 1.55 times
its volume at 2 s under it, 2.02 under BDF2 and under backward Euler at dt / 10. BDF2 is not yet
"auto"'s choice there: in float32 its extrapolated guess, accepted within round-off, leaves a
damped body at rest jittering above the sleep threshold (a settling box never slept in 600
steps). In a damped scene BDF2 starts with one backward Euler step (`History.target`): run back
in time a damped mode grows.

Fields (n vertices of the capacity), made on the first step that needs them:
    x_prev, v_prev (n, 3)   BDF2: x_(n-1) (m), v_(n-1) (m/s), the start of the last step
    accel (n, 3)            trapezoidal: a_n (m/s^2), the acceleration where the last step ended
"""

import math
from dataclasses import dataclass

import taichi as ti

@dataclass(frozen=True)
class Target:
    """x^ = a x_n + b x_(n-1) + c h v_n, v^ = a v_n + b v_(n-1) + c h a_n; h = h_per_dt dt."""

    name: str
    a: float
    b: float
    h_per_dt: float
    c: float = 0.0

    @property
    def from_history(self):
        """Built from the last step too: the step starts from its guess, not from v = 0."""
        return self.b != 0.0 or self.c != 0.0


    @property
    def one_step(self):
        """The theta family (the trapezoidal rule and its damped kin): a_n, not x_(n-1), carries the history."""
        return self.c != 0.0


def theta_rule(rho):
    """The generalised trapezoidal rule with numerical dissipation rho_infinity = rho in [0, 1]:
    x_(n+1) = x_n + dt ((1 - theta) v_n + theta v_(n+1)), v likewise with a, theta = 1 / (1 + rho),
    so x^ = x_n + rho h v_n, v^ = v_n + rho h a_n with h = theta dt. A mode far faster than 1/dt
    is multiplied by -rho each step (rho = 1: the trapezoidal rule, which keeps it; rho = 0:
    backward Euler, which removes it at once); one resolved at frequency omega loses about
    (theta - 1/2) (omega dt)^2 of its energy a step, so rho near 1 damps only what dt cannot
    follow."""
    name = "trapezoidal" if rho == 1.0 else f"trapezoidal (rho_infinity {rho:.3g})"   # what the step is
    return Target(name, 1.0, 0.0, 1.0 / (1.0 + rho), rho)


# The trapezoidal rule's numerical dissipation by default (`default_rho`). With Rayleigh damping D = alpha M +
# beta K a stiff mode's continuous decay is fast, but rho = 1 maps a mode decaying far faster than 1/dt to a
# factor -1 a step, and a damped body would ring for ever (a cantilever with alpha 5 at dt 0.5 s rang after
# 2,000 steps). A fixed rho < 1 costs the rule its order: a resolved mode loses (theta - 1/2) (omega dt)^2 a
# step more than its damping's share, first order in dt (rho 0.9: observed order 1.03 to 1.15 on a damped
# bar). rho = exp(-dt / DAMPED_TAU) makes the modes dt cannot follow decay by e every DAMPED_TAU seconds of
# simulated time whatever dt is, and theta - 1/2 = dt / (4 DAMPED_TAU) + O(dt^3), so the rule stays second
# order (2.01 and 2.07 on that bar). 0.5 s (rho 0.961 at dt 0.02 s) was chosen on the benchmark's damped
# scenes (docs/method.md, section 6).
DAMPED_TAU = 0.5          # s
# A ground's or contact's penalty is far stiffer than any body and rings under the trapezoidal rule:
# it takes at most this rho whatever dt is (auto takes BDF2 there)
PENALTY_RHO = 0.9


def default_rho(dt, damped, penalty):
    """rho_infinity when the scene names none: 1 (the conserving trapezoidal rule), exp(-dt / DAMPED_TAU)
    with Rayleigh damping, at most PENALTY_RHO with a ground's or contact's penalty."""
    rho = math.exp(-dt / DAMPED_TAU) if damped else 1.0
    return min(rho, PENALTY_RHO) if penalty else rho


def spin_law(target, dt, alpha):
    """What a one-step rule's drag alpha M leaves of a free body's angular momentum over a step,
    L_(n+1) = L_n (1 - (1 - theta) dt alpha) / (1 + theta dt alpha) with theta = h / dt (exp(-alpha dt)
    to second order at theta = 1/2; internal forces, damping's too, turn no body)."""
    theta = target.h_per_dt
    return (1.0 - (1.0 - theta) * dt * alpha) / (1.0 + theta * dt * alpha)


BACKWARD_EULER = Target("backward-euler", 1.0, 0.0, 1.0)
BDF2 = Target("bdf2", 4.0 / 3.0, -1.0 / 3.0, 2.0 / 3.0)
TRAPEZOIDAL = theta_rule(1.0)
TWO_STEP = ("bdf2", "trapezoidal")     # the integrators that need the last step


def described(settings, damped, penalty):
    """The name the steps of these settings carry (StepInfo.integrator) at settings.dt: "bdf2",
    "trapezoidal", "trapezoidal (rho_infinity 0.9)". penalty: the scene has a ground or contact."""
    integrator = chosen(settings.integrator, penalty)
    if integrator != "trapezoidal":
        return integrator
    rho = settings.rho_infinity if settings.rho_infinity is not None else default_rho(settings.dt, damped, penalty)
    return theta_rule(rho).name


def penalty_note(settings, where):
    """The one line that tells a user who asked for the trapezoidal rule in a scene with a ground
    or contact (and no rho_infinity) what the steps take instead, and why; None otherwise."""
    if settings.integrator != "trapezoidal" or settings.rho_infinity is not None:
        return None
    return (f"note: {where}: with a ground or contact the trapezoidal rule takes rho_infinity {PENALTY_RHO:g} "
            f"(numerical dissipation, first order) so that the contact penalty does not ring; "
            f"set solver.rho_infinity = 1 for the rule itself")


def chosen(integrator, ground):
    """The integrator a step takes: `integrator`, or for "auto" BDF2 with a ground or contact, else trapezoidal."""
    if integrator != "auto":
        return integrator
    return "bdf2" if ground else "trapezoidal"


@ti.data_oriented
class History:
    """What a two-step integrator keeps of the last step; `sleep`: a sleeping body's target is x_n."""

    def __init__(self, model, sleep, switches):
        self.model, self.sleep = model, sleep
        self.serial_vertices = switches.serial_vertices
        self.x_prev = self.v_prev = None                  # made on first use: backward Euler needs none
        self.accel = ti.Vector.field(3, float, model.capacity.vertices)   # the step's safeguards write it
        self.forget()

    def forget(self):
        """The next step starts the history again (backward Euler)."""
        self.dt = None                            # s: the dt of the step whose start is kept
        self.integrator = None                    # and the integrator that kept it
        self.version = None                       # and the model's version (materials, methods) then
        self.fresh = False                        # the next step's a_n comes from its start's forces

    def target(self, integrator, dt, version=None, rho=1.0, damped=False):
        """The Target of the next step of `integrator` at dt (version: the model's, whose forces
        a_n was taken with). The trapezoidal rule is a one-step scheme: it needs a_n, which the
        last step's update gives, or else the forces at the step's start (`fresh`: the solver
        computes it there). BDF2 needs the last step: where there is none, its x_(n-1), v_(n-1) are
        read off x_n, v_n and a_n (`apply`), so that no step of a second-order run is first order.
        With Rayleigh damping (`damped`) BDF2 starts with a backward Euler step instead: run back
        in time a damped mode grows, and the expansion back from a struck body (the coursework's
        epcot, beta 0.1) made a history whose first step rose in energy, was trimmed and lost
        every deformation, at any dt. One first-order step keeps the run second order."""
        known = (self.dt, self.integrator, self.version) == (dt, integrator, version)
        self.fresh = integrator in TWO_STEP and not known
        if integrator == "bdf2" and self.fresh and damped:
            self.fresh = False                    # apply keeps x_n, v_n as the next step's history
            return BACKWARD_EULER
        if integrator == "bdf2":
            return BDF2
        if integrator == "trapezoidal":
            return theta_rule(rho)
        return BACKWARD_EULER

    def apply(self, target, integrator, potential, x, v, h, dt):
        """x0, v0 of the potential (x_n, v_n after its `begin`) <- the target's x^, v^ (h: its
        effective step); for BDF2, the step's start (x, v) is then kept as the next step's
        x_(n-1), v_(n-1) (one launch; `remember` says whether the next step may use it). A BDF2
        step with no last step (`fresh`) takes x_(n-1) = x_n - dt v_n + dt^2 a_n / 2 and
        v_(n-1) = v_n - dt a_n, the Taylor expansion back from its start: second order, and as
        stable as BDF2 (a first step by the trapezoidal rule rang on the ground's penalty)."""
        if integrator == "bdf2":
            if self.x_prev is None:
                n = self.model.capacity.vertices
                self.x_prev, self.v_prev = ti.Vector.field(3, float, n), ti.Vector.field(3, float, n)
            if self.fresh:
                self.extrapolate(x, v, dt)
            self.advance(potential.x0, potential.v0, x, v, target.a, target.b, int(target.b != 0.0))
        if target.one_step:
            self.half_step(potential.x0, potential.v0, target.c * h)

    def remember(self, integrator, dt, version=None):
        """After a good step at dt: the next step of a two-step integrator may use what `apply`
        kept (BDF2) or the acceleration the step's safeguards kept (trapezoidal)."""
        if integrator not in TWO_STEP:
            self.forget()
            return
        self.dt, self.integrator, self.version = dt, integrator, version

    def acceleration(self):
        """The field of a_n, which the step's safeguards write."""
        return self.accel

    @ti.kernel
    def advance(self, x0: ti.template(), v0: ti.template(), x: ti.template(), v: ti.template(), a: float,
                b: float, multistep: ti.i32):
        """x0, v0 <- a x_n + b x_(n-1), a v_n + b v_(n-1) (multistep; a sleeping body keeps x_n,
        v_n: it rests exactly); then x_(n-1), v_(n-1) <- x, v, this step's start."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if multistep and self.sleep.awake[self.model.vertex_body[i]]:
                x0[i] = a * x0[i] + b * self.x_prev[i]
                v0[i] = a * v0[i] + b * self.v_prev[i]
            self.x_prev[i], self.v_prev[i] = x[i], v[i]

    @ti.kernel
    def extrapolate(self, x: ti.template(), v: ti.template(), dt: float):
        """x_(n-1), v_(n-1) <- x_n - dt v_n + dt^2 a_n / 2, v_n - dt a_n."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.x_prev[i] = x[i] - dt * v[i] + 0.5 * dt * dt * self.accel[i]
            self.v_prev[i] = v[i] - dt * self.accel[i]

    @ti.kernel
    def half_step(self, x0: ti.template(), v0: ti.template(), h: float):
        """x0, v0 <- x_n + h v_n, v_n + h a_n (h: rho times the step's h; a sleeping body keeps x_n, v_n)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            if self.sleep.awake[self.model.vertex_body[i]]:
                x0[i] += h * v0[i]
                v0[i] += h * self.accel[i]
