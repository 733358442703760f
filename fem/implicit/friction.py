"""Coulomb friction between contact pairs (fem/implicit/contact.py), lagged as IPC lags it.

The pairs touching at the step's first iterate (`lag`) keep, for the whole step, their weights
c, their normal n and their normal force lambda = -k m_p b'(d) (N, the barrier's push there,
fem/implicit/pair_geometry.py). Each adds to E(v)

    h mu lambda f0(|u_T|),   u_T = (I - n n^T) sum_a c_a v_a   (J)

u_T the pair's relative tangential velocity and f0 IPC's smoothed speed (`friction_shape` in
fem/implicit/effects.py, the ground's): a pair that slides loses mu lambda of force, one nearly at
rest sticks. Its gradient is h mu lambda f1(s) / s u_T on each point by its weight, its Hessian
h mu lambda (f1(s) / s (I - n n^T - t t^T) + f1'(s) t t^T) on the pair's 12 dofs, t = u_T / s:
positive semi-definite, so H stays SPD for PCG.

Fields (P pairs of the contact's capacity):
    sticks (P, 2)          the step's friction pairs, as the contact's pairs (vertex, triangle) or edges
    stick_count ()         how many
    stick_weights (P, 4)   c at the step's start
    stick_normal (P, 3)    n at the step's start
    stick_force (P,)       lambda, N
    stick_matrix (P, 3x3)  the pair's Hessian block h mu lambda (...), kg/s
"""

import taichi as ti


@ti.data_oriented
class PairFriction:
    """The lagged friction of one model's contact pairs; `contact` gives their vertices and mu."""

    def __init__(self, contact, capacity):
        self.contact = contact
        self.sticks = ti.Vector.field(2, ti.i32, capacity)
        self.stick_count = ti.field(ti.i32, ())
        self.stick_weights = ti.Vector.field(4, float, capacity)
        self.stick_normal = ti.Vector.field(3, float, capacity)
        self.stick_force = ti.field(float, capacity)
        self.stick_matrix = ti.Matrix.field(3, 3, float, capacity)

    @ti.func
    def clear(self):
        self.stick_count[None] = 0

    @ti.func
    def lag(self, pair, c, n, force):
        """A pair touching at the step's start (weights c, normal n, normal force in N) rubs
        for the whole step."""
        k = ti.atomic_add(self.stick_count[None], 1)
        self.sticks[k] = pair
        self.stick_weights[k], self.stick_normal[k], self.stick_force[k] = c, n, force

    @ti.func
    def evaluate(self, v: ti.template(), h, body_E: ti.template(), force: ti.template(), block: ti.template()):
        """body_E += each pair's h mu lambda f0(|u_T|) (J, float64); force += its -grad (N s);
        stick_matrix and block += its Hessian (kg/s), at the velocities v."""
        mu = self.contact.friction[None]
        ti.loop_config(serialize=self.contact.serial_vertices)
        for q in range(self.stick_count[None] * (mu > 0)):
            ids = self.contact.corners(self.sticks[q])[0]
            c, n = self.stick_weights[q], self.stick_normal[q]
            u = c[0] * v[ids[0]] + c[1] * v[ids[1]] + c[2] * v[ids[2]] + c[3] * v[ids[3]]
            u -= u.dot(n) * n                                  # tangential relative velocity
            s = u.norm()
            f0, across, along = self.contact.effects.friction_model(s)
            lam = h * mu * self.stick_force[q]
            body_E[self.contact.model.vertex_body[ids[0]]] += ti.cast(lam, ti.f64) * ti.cast(f0, ti.f64)
            g = lam * across
            t = u / ti.max(s, 1e-30)
            A = g * (ti.Matrix.identity(float, 3) - n.outer_product(n)) + lam * (along - across) * t.outer_product(t)
            self.contact.scatter(force, ids, c, -g * u)
            for a in ti.static(range(4)):
                block[ids[a]] += c[a] * c[a] * A
            self.stick_matrix[q] = A

    @ti.func
    def product(self, z: ti.template(), p: ti.template(), beta, on, out: ti.template()):
        """out += (friction's Hessian) u, u = z + beta p. on = 0: loops over nothing."""
        ti.loop_config(serialize=self.contact.serial_vertices)
        for q in range(self.stick_count[None] * on * (self.contact.friction[None] > 0)):
            ids, c = self.contact.corners(self.sticks[q])[0], self.stick_weights[q]
            s = ti.Vector.zero(float, 3)
            for a in ti.static(range(4)):
                s += c[a] * (z[ids[a]] + beta * p[ids[a]])
            self.contact.scatter(out, ids, c, self.stick_matrix[q] @ s)
