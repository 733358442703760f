"""A stiff body's Newton trials: the turn Newton's direction gives it, taken on its arc.

Newton's direction d is a velocity, and a trial iterate moves every vertex along it:
x = x_k + h a d (x_k the accepted iterate, a the line search's step). Where d turns a body,
w = h a omega_d, that is the turn's tangent, which stretches every tet by |w|^2 / 2: no
Newton model sees it, and a nearly incompressible body answers it with lam |w|^2 / 2 of
pressure. A 0.5 m cube at E 1e11, nu 0.49995 spinning at 10 rad/s (lam 3.3e14 Pa) whose
iterates' spin Newton corrects by 1e-3 (|w| about 1e-4) got 1e6 to 1e9 Pa where the answer's
pressure is 5.6e3 Pa; the next iteration took that pressure out by turning the body again, and
the iteration went back and forth (89 of 100 steps unconverged, 74 trimmed, under the
energy-momentum step; under BDF2 and backward Euler 50 of 50 unconverged).

So a body too stiff for dt to follow, in shear too (Model.stiff(dt, shear=True): a nearly
incompressible jelly deforms through the step, and the ground drops' one converged less often on
the arc), with no vertex pinned, pressed into the ground or within a step's reach of it (`begin`:
there the ground, not its spin, turns it), takes the rotational part of d,
omega_d = I^-1 sum m r x d about its centre c at x_k, on its arc:

    x = x_k + h a d + (Rot(w) - I) r - w x r,   r = x_k - c,  w = h a omega_d,

(Rot(w) - I) r - w x r = (sin|w| / |w| - 1) w x r + (1 - cos|w|) / |w|^2 w x (w x r): a point
on a curve whose tangent at a = 0 is d, so the line search's slope and Newton's convergence
are unchanged, and a rigid turn of d strains nothing. The trial's velocity is (x - x_0) / h.

Fields (bodies of the capacity):
    centre (bodies, 3)   c, the body's centre of mass at x_k, m (float64)
    spin (bodies, 3)     omega_d, the spin of d about c, rad/s (float64)
    on (bodies,)         1: the body's trials take the arc
"""

import taichi as ti

F64 = ti.f64


@ti.data_oriented
class Bend:
    """The arc of a stiff free body's trial iterates: `prepare` after each direction, `correction` per vertex."""

    def __init__(self, model, stiff, effects, sleep):
        nb = model.capacity.bodies
        self.model, self.stiff, self.effects, self.sleep = model, stiff, effects, sleep
        self.centre = ti.Vector.field(3, F64, nb)
        self.spin = ti.Vector.field(3, F64, nb)
        self.on = ti.field(ti.i32, nb)
        self.grounded = ti.field(ti.i32, nb)

    @ti.kernel
    def begin(self, x_n: ti.template(), v_n: ti.template(), dt: float):
        """`grounded` <- 1 for a body with a vertex the step may carry into the ground: at x_n within
        dt (|v_n| + |g| dt) of it (a body resting or landing on it, which the ground, not its spin, turns)."""
        self.sleep.sums.reduce(self.near, self.store_near, (x_n, v_n, dt))

    @ti.func
    def near(self, i, b, data: ti.template()):
        x_n, v_n = ti.static(data[0], data[1])
        dt = data[2]
        reach = dt * (v_n[i].norm() + self.effects.gravity[None].norm() * dt)
        near = 0.0
        if ti.static(self.effects.has_ground):
            near = ti.cast(x_n[i][1] - self.effects.ground[None] <= reach, F64)
        return ti.Vector([near, 0, 0, 0, 0, 0, 0, 0, 0, 0], F64)

    @ti.func
    def store_near(self, b, total, data: ti.template()):
        self.grounded[b] = int(total[0] > 0)

    @ti.kernel
    def prepare(self, x0: ti.template(), velocity: ti.template(), d: ti.template(), h: float):
        """c and omega_d of every body at x_k = x0 + h velocity (`on`: stiff in shear too, massive, not
        `grounded`, and neither pinned nor pressed into the ground at x_k: there the ground turns it)."""
        self.sleep.sums.reduce(self.moments, self.store_centre, (x0, velocity, h))
        self.sleep.sums.reduce(self.turning, self.store_spin, (x0, velocity, d, h))

    @ti.func
    def moments(self, i, b, data: ti.template()):
        """Vertex i's (m, m x_k, 1 where it is pinned, 1 where x_k presses it into the ground)."""
        x0, velocity = ti.static(data[0], data[1])
        h = data[2]
        m = ti.cast(self.model.mass[i], F64)
        x = x0[i] + h * velocity[i]
        q = m * ti.cast(x, F64)
        return ti.Vector([m, q[0], q[1], q[2], ti.cast(1 - self.model.free[i], F64),
                          ti.cast(self.effects.pressed(x), F64), 0, 0, 0, 0], F64)

    @ti.func
    def store_centre(self, b, total, data: ti.template()):
        self.on[b] = int(self.stiff[b] == 2 and total[4] == 0 and total[5] == 0 and total[0] > 0 and
                         self.grounded[b] == 0)
        self.centre[b] = ti.Vector([total[1], total[2], total[3]]) / ti.max(total[0], 1e-300)

    @ti.func
    def turning(self, i, b, data: ti.template()):
        """Vertex i's (m r x d, m (r.r I - r r^T) as xx yy zz xy xz yz), r = x_k - c."""
        x0, velocity, d = ti.static(data[0], data[1], data[2])
        h = data[3]
        m = ti.cast(self.model.mass[i], F64)
        r = ti.cast(x0[i] + h * velocity[i], F64) - self.centre[b]
        L = m * r.cross(ti.cast(d[i], F64))
        return ti.Vector([L[0], L[1], L[2], m * (r[1] * r[1] + r[2] * r[2]), m * (r[0] * r[0] + r[2] * r[2]),
                          m * (r[0] * r[0] + r[1] * r[1]), -m * r[0] * r[1], -m * r[0] * r[2], -m * r[1] * r[2], 0],
                         F64)

    @ti.func
    def store_spin(self, b, total, data: ti.template()):
        I = ti.Matrix([[total[3], total[6], total[7]], [total[6], total[4], total[8]],
                       [total[7], total[8], total[5]]], F64)
        self.spin[b] = ti.Vector.zero(F64, 3)
        if self.on[b] and I.determinant() > 1e-12 * I.trace() ** 3:
            self.spin[b] = I.inverse() @ ti.Vector([total[0], total[1], total[2]])
        else:
            self.on[b] = 0

    @ti.func
    def correction(self, i, x0: ti.template(), velocity: ti.template(), a, h):
        """What vertex i's trial velocity gains on its body's arc: ((Rot(w) - I) r - w x r) / h."""
        b = self.model.vertex_body[i]
        out = ti.Vector.zero(F64, 3)
        if self.on[b]:
            r = ti.cast(x0[i] + h * velocity[i], F64) - self.centre[b]
            w = ti.cast(h * a, F64) * self.spin[b]
            t2 = w.norm_sqr()
            along, across = -t2 / 6.0, 0.5 - t2 / 24.0                 # series below |w| = 1e-3
            if t2 > 1e-6:
                t = ti.sqrt(t2)
                along, across = ti.sin(t) / t - 1.0, (1.0 - ti.cos(t)) / t2
            wr = w.cross(r)
            out = (along * wr + across * w.cross(wr)) / ti.cast(h, F64)
        return ti.cast(out, float)
