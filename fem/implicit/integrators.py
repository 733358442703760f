"""The integrators: what each one puts into the incremental potential (fem/implicit/potential.py).

For this solver an implicit integrator is an inertia target (x^, v^) and an effective step h:
the step's velocity v minimises E(v) built from them, and x_(n+1) = x^ + h v.

    backward-euler   x^ = x_n,                     v^ = v_n,                     h = dt
    bdf2             x^ = (4 x_n - x_(n-1)) / 3,   v^ = (4 v_n - v_(n-1)) / 3,   h = 2 dt / 3

Backward Euler is first order: its error is a damping of every motion, of order omega^2 dt
per second for a mode of frequency omega, and it dominates what a spinning or wobbling body
loses. BDF2 (the two-step backward differentiation formula) is second order and damps only
at order omega^4 dt^3. It needs the previous step: the first step of a run, and the first
after anything that breaks the history (an impulse, a new state, a change of dt, a rejected
step), is backward Euler (`History.target`). Sleeping bodies keep their place exactly.

Fields (n vertices of the capacity), made on the first BDF2 step:
    x_prev, v_prev (n, 3)   x_(n-1) (m), v_(n-1) (m/s): the start of the last step
"""

from dataclasses import dataclass

import taichi as ti

@dataclass(frozen=True)
class Target:
    """x^ = a x_n + b x_(n-1) (v^ likewise), h = h_per_dt dt."""

    name: str
    a: float
    b: float
    h_per_dt: float


BACKWARD_EULER = Target("backward-euler", 1.0, 0.0, 1.0)
BDF2 = Target("bdf2", 4.0 / 3.0, -1.0 / 3.0, 2.0 / 3.0)


@ti.data_oriented
class History:
    """The last step's start, for a two-step integrator; `sleep`: a sleeping body's target is x_n."""

    def __init__(self, model, sleep, switches):
        self.model, self.sleep = model, sleep
        self.serial_vertices = switches.serial_vertices
        self.x_prev = self.v_prev = None          # made on first use: backward Euler needs none
        self.forget()

    def forget(self):
        """The next step starts the history again (backward Euler)."""
        self.dt = None                            # s: the dt of the step whose start is kept

    def target(self, integrator, dt):
        """The Target of the next step of `integrator` at dt."""
        if integrator == "bdf2" and self.dt == dt:
            return BDF2
        return BACKWARD_EULER

    def apply(self, target, integrator, potential, x, v):
        """x0, v0 of the potential (x_n, v_n after its `begin`) <- the target's x^, v^; for a
        two-step integrator, the step's start (x, v) is then kept as the next step's x_(n-1),
        v_(n-1) (one launch; `remember` says whether the next step may use it)."""
        if integrator != "bdf2":
            return
        if self.x_prev is None:
            n = self.model.capacity.vertices
            self.x_prev, self.v_prev = ti.Vector.field(3, float, n), ti.Vector.field(3, float, n)
        self.advance(potential.x0, potential.v0, x, v, target.a, target.b, int(target.b != 0.0))

    def remember(self, integrator, dt):
        """After a good step at dt: the next step of a two-step integrator may use the start
        `apply` kept."""
        if integrator != "bdf2":
            self.forget()
            return
        self.dt = dt

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
