"""Contact between bodies, and of a body with itself: an energy inside E(v) (method.md, section 6).

Each surface vertex p and each surface triangle t = (t0, t1, t2) that does not contain it, of
another body or of the same one, are a pair; so are two surface edges that share no vertex (a
thin plate's edge can cut through a block's edge with no vertex of either inside the other).
With d = |r| the distance between the pair's closest points (`points_gap`: r = p - sum_j w_j t_j,
w the barycentric weights of the triangle's point closest to p; for edges r = a(s) - b(t)), the
pair stores

    C(x) = -k m_p (d_hat - d)^2 ln(d / d_hat)  for d < d_hat,   k = PAIR_STIFFNESS / dt^2   (J)

IPC's log barrier (Li et al. 2020, `barrier` in fem/implicit/pair_geometry.py) across a contact thickness d_hat (the scene's
`distance`), as stiff as the ground's penalty (fem/implicit/effects.py). It has no kink at d_hat
and grows without bound as d -> 0: a penalty k m_p / 2 (d_hat - d)^2 stores at most
k m_p d_hat^2 / 2, less than a plate at 100 m/s brings, and the step's minimisation pushed such
pairs together until they crossed. Its gradient is exact: grad_p d = n = (p - c) / d, grad_tj d =
-w_j n (c is the closest point, so moving it along the triangle changes d to first order by
nothing). Its Hessian is Gauss-Newton's, k m_p b''(d) n n^T on the pair's 12 dofs weighted by
(1, -w0, -w1, -w2): positive semi-definite, so H stays SPD for PCG. C only depends on the
positions, not on which pairs were found, as long as the broad phase finds every pair closer
than d_hat.

Friction is lagged as the ground's (fem/implicit/friction.py): the pairs touching at the step's
start keep their weights, normal and normal force lambda = -k m_p b'(d) for the whole step.

Newton's stopping test cannot ask more of the gradient than its round-off: a pair's push changes
by h k m_p b''(d) per metre of d, and d is known to eps |x| (f32: 3e-8 m at 0.4 m from the
origin), 2 to 7 times the tolerance of a box resting on another in f32 (`body_noise`).

No vertex passes through a triangle: each line search starts with a step bound (`prepare_search`,
additive CCD, Li et al. 2021, `time_of_impact`): a pair whose four points move by at most D
relative to their mean along the step closes at most D a, so it may advance by SAFETY d(a) / D
at a time, d(a) its distance there, until it has closed SAFETY of its first gap d0. A pair that
slides along its triangle, or moves with it, keeps the full step. The same pass finds the pairs
for the line search, from a broad phase (fem/implicit/broad_phase.py, a spatial hash: O(n)): every
pair closer than d_hat + m_a + m_b, m the most a side's points move along the step (|h d_i|), the
only ones that can come closer than d_hat; and the islands of bodies they join, each searching alone.

Fields (n vertices, t triangles of the capacity, P pairs):
    triangles (t, 3)       the surface triangles' global vertex ids, outward (counter-clockwise)
    surface (n,)           the surface vertices' ids, surface_count of them
    distance ()            d_hat, m
    friction ()            mu, Coulomb's coefficient between bodies
    reach ()               m: the most a line search moves a vertex before its step is cut
    island (bodies,)       the lowest body id joined to a body by candidate pairs (the broad phase's)
    edges (e, 2)           the surface edges (sorted vertex ids, in order)
    pairs (P, 2)           candidate pairs of the current search: (vertex, triangle), or
                           (-e - 1, f) for edges e < f (`corners`)
    close_ids (P, 4)       the four vertices of each pair closer than d_hat at the last evaluation, close_count
                           of them: the products H u loop over these alone (the pile's first CG: 130 of 4,500)
    pair_weights (P, 4)    their c (`points_gap`)
    pair_matrix (P, 3x3)   their h^2 k m_p b"(d) n n^T (kg/s)
    sticking               the step's friction pairs (PairFriction, fem/implicit/friction.py)
    force (n, 3)           -grad of the contact and friction terms at the last evaluation, N s
    product (n, 3)         (their Hessian) u of the last product pass, N s
    block (n, 3x3)         their Hessian's diagonal blocks, for the preconditioner (kg/s)
    body_noise (bodies,)   the round-off of |grad_b|^2 from the pairs' distances at the last
                           evaluation, sum (NOISE eps h k m_p b''(d) sum_a |c_a| |x_a|)^2 c_a^2, (N s)^2
    energy (n,)            each vertex's share of the contact energy (half of each pair to either
                           vertex, half to its triangle's), J, float64: the safeguards' per-body sums
"""

import numpy as np
import taichi as ti

from fem.implicit.broad_phase import BroadPhase
from fem.implicit.friction import PairFriction
from fem.implicit.pair_geometry import TOUCHING, barrier, closing_bound, points_gap
from fem.runtime import epsilon

SAFETY = 0.9                 # a line search step closes at most this share of any pair's gap
PAIRS_PER_VERTEX = 64        # room for candidate pairs; more are dropped, and the run warns (fem/simulation.py)
MOLLIFIER = 1e-3             # edges closer to parallel than sin^2 = this fade out (`Contact.mollifier`)
ADVANCES = 32                # additive CCD's conservative advances per pair and line search
# k dt^2 of the pairs' barrier, in units of a vertex's inertia over one step, as the ground's. Measured at 30:
# two_boxes converged on every f64 step (58 of 60 at 1000), the pile no more often (19 of 60), and a box
# resting on a slab in f32 on 105 of 110 steps (110 at 1000)
PAIR_STIFFNESS = 1000.0
NOISE = 2.0                  # a distance's round-off, in units of eps sum_a |c_a| |x_a|


@ti.data_oriented
class Contact:
    """The contact pairs of one model: broad phase, energy, gradient, Hessian products."""

    def __init__(self, model, effects, switches):
        n, t = model.capacity.vertices, 4 * model.capacity.tets
        self.model, self.effects = model, effects
        self.serial_vertices = switches.serial_vertices
        self.pair_capacity = PAIRS_PER_VERTEX * n
        self.triangles = ti.Vector.field(3, ti.i32, t)
        self.triangle_count = ti.field(ti.i32, ())
        self.surface = ti.field(ti.i32, n)
        self.surface_count = ti.field(ti.i32, ())
        self.edges = ti.Vector.field(2, ti.i32, 3 * t // 2 + 3)
        self.edge_count = ti.field(ti.i32, ())
        self.distance = ti.field(float, ())
        self.stiffness = ti.field(float, ())
        self.friction = ti.field(float, ())
        self.reach = ti.field(float, ())
        self.pairs = ti.Vector.field(2, ti.i32, self.pair_capacity)
        self.pair_count = ti.field(ti.i32, ())
        self.overflow = ti.field(ti.i32, ())
        self.broad = BroadPhase(model, self, switches)
        self.island = self.broad.island
        self.close_ids = ti.Vector.field(4, ti.i32, self.pair_capacity)
        self.close_count = ti.field(ti.i32, ())
        self.pair_weights = ti.Vector.field(4, float, self.pair_capacity)
        self.pair_matrix = ti.Matrix.field(3, 3, float, self.pair_capacity)
        self.sticking = PairFriction(self, self.pair_capacity)
        self.body_noise = ti.field(ti.f64, model.capacity.bodies)
        self.force = ti.Vector.field(3, float, n)
        self.product = ti.Vector.field(3, float, n)
        self.block = ti.Matrix.field(3, 3, float, n)
        self.energy = ti.field(ti.f64, n)
        self.step_limit = ti.field(float, ())
        self.body_limit = ti.field(float, model.capacity.bodies)
        self.largest_move = ti.field(float, ())
        self.smallest = ti.field(float, ())
        self.touching = ti.field(ti.i32, ())
        self.crossing = ti.field(ti.i32, ())

    def load(self, contact):
        """The model's surface and a scene's contact settings (fem.scene.ContactEffect)."""
        triangles = self.model.surface.astype(np.int32)
        surface = np.unique(triangles).astype(np.int32)
        self.model.write(self.triangles, triangles)
        self.model.write(self.surface, surface)
        self.triangle_count[None], self.surface_count[None] = len(triangles), len(surface)
        sides = np.sort(np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2), axis=2).reshape(-1, 2)
        edges = np.unique(sides, axis=0)
        self.model.write(self.edges, edges.astype(np.int32))
        self.edge_count[None] = len(edges)
        rest = self.model.rest_positions_np
        edges = np.linalg.norm(rest[triangles] - rest[np.roll(triangles, 1, axis=1)], axis=2)
        self.reach[None] = max(float(edges.mean()), 4.0 * contact.distance)
        self.distance[None], self.friction[None] = contact.distance, contact.friction
        self.sticking.stick_count[None] = 0
        self.broad.forget()

    def set_dt(self, dt):
        """The barrier's stiffness k = PAIR_STIFFNESS / dt^2 follows the scene's dt, as the ground's."""
        self.stiffness[None] = PAIR_STIFFNESS / (dt * dt)

    # ------------------------------------------------------------ one pair

    @ti.func
    def corners(self, pair):
        """A pair's four vertices and its kind: (p, t0, t1, t2), 0 for a vertex and a triangle
        (pair = (p, triangle)); (a0, a1, b0, b1), 1 for two edges (pair = (-e - 1, f))."""
        ids, edge = ti.Vector([0, 0, 0, 0]), int(pair[0] < 0)
        if edge:
            a, b = self.edges[-pair[0] - 1], self.edges[pair[1]]
            ids = ti.Vector([a[0], a[1], b[0], b[1]])
        else:
            t = self.triangles[pair[1]]
            ids = ti.Vector([pair[0], t[0], t[1], t[2]])
        return ids, edge

    @ti.func
    def vertices(self, q):
        """Candidate pair q's four vertices and kind (`corners`)."""
        return self.corners(self.pairs[q])

    @ti.func
    def gap(self, x: ti.template(), ids, edge):
        """`points_gap` of the pair with vertices ids, of kind edge, at x."""
        return points_gap(x[ids[0]], x[ids[1]], x[ids[2]], x[ids[3]], edge)

    @ti.func
    def mollifier(self, x: ti.template(), ids, edge):
        """IPC's mollifier of an edge-edge pair (Li et al. 2020), which fades its energy out as the
        edges turn parallel, where their closest points jump and d has no gradient:
        m(y) = (2 - y / eps) y / eps below eps, 1 above, y = |e0 x e1|^2, eps = MOLLIFIER
        |E0|^2 |E1|^2 (rest lengths). Returns (m, m'(y), grad_e0 y, grad_e1 y); (1, 0, 0, 0) for a
        vertex and a triangle."""
        mol, slope = 1.0, 0.0
        grad0, grad1 = ti.Vector([0.0, 0.0, 0.0]), ti.Vector([0.0, 0.0, 0.0])
        if edge:
            e0, e1 = x[ids[1]] - x[ids[0]], x[ids[3]] - x[ids[2]]
            r = ti.static(self.model.rest_positions)
            eps = ti.static(MOLLIFIER) * (r[ids[1]] - r[ids[0]]).norm_sqr() * (r[ids[3]] - r[ids[2]]).norm_sqr()
            cross = e0.cross(e1)
            y = cross.norm_sqr()
            if y < eps:
                mol, slope = (2.0 - y / eps) * y / eps, (2.0 - 2.0 * y / eps) / eps
                grad0, grad1 = 2.0 * e1.cross(cross), 2.0 * cross.cross(e0)
        return mol, slope, grad0, grad1

    @ti.func
    def pair_mass(self, ids, edge):
        """m_p: the vertex's mass, or the mean of the two edges' four (kg)."""
        m = self.model.mass[ids[0]]
        if edge:
            m = 0.25 * (m + self.model.mass[ids[1]] + self.model.mass[ids[2]] + self.model.mass[ids[3]])
        return m

    @ti.func
    def scatter(self, out: ti.template(), ids, weights, f):
        for a in ti.static(range(4)):
            ti.atomic_add(out[ids[a]], weights[a] * f)

    # ------------------------------------------------------------ E, grad E, H u

    @ti.func
    def evaluate(self, x: ti.template(), v: ti.template(), h, body_E: ti.template()):
        """body_E += the contact and friction energies (J, float64); force <- their -grad E
        (N s); pair_matrix, stick_matrix and block <- their Hessian (kg/s); body_noise <- the
        round-off of each body's gradient, at (x, v)."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.force[i] = ti.Vector.zero(float, 3)
            self.block[i] = ti.Matrix.zero(float, 3, 3)
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_noise[b] = 0.0
        d_hat = self.distance[None]
        self.close_count[None] = 0
        ti.loop_config(serialize=self.serial_vertices)
        for q in range(self.pair_count[None]):
            ids, edge = self.vertices(q)
            d, n, c = self.gap(x, ids, edge)
            km = self.stiffness[None] * self.pair_mass(ids, edge)
            if d < d_hat:
                phi, push, curve = barrier(d, d_hat)
                mol, slope, grad0, grad1 = self.mollifier(x, ids, edge)
                body_E[self.model.vertex_body[ids[0]]] += ti.cast(km * mol, ti.f64) * phi
                self.scatter(self.force, ids, c, h * km * mol * push * n)
                if edge:                                       # -h grad of the mollifier's factor
                    pull = h * km * ti.cast(phi, float) * slope
                    f0, f1 = pull * grad0, pull * grad1
                    ti.atomic_add(self.force[ids[0]], f0)
                    ti.atomic_sub(self.force[ids[1]], f0)
                    ti.atomic_add(self.force[ids[2]], f1)
                    ti.atomic_sub(self.force[ids[3]], f1)
                A = h * h * km * mol * curve * n.outer_product(n)
                k = ti.atomic_add(self.close_count[None], 1)
                self.close_ids[k], self.pair_weights[k], self.pair_matrix[k] = ids, c, A
                size = 0.0                                     # sum_a |c_a| |x_a|: d's round-off / eps
                for a in ti.static(range(4)):
                    self.block[ids[a]] += c[a] * c[a] * A
                    size += ti.abs(c[a]) * x[ids[a]].norm()
                noise = ti.cast(ti.static(NOISE * epsilon()) * h * km * mol * curve * size, ti.f64) ** 2
                for a in ti.static(range(4)):
                    self.body_noise[self.model.vertex_body[ids[a]]] += noise * ti.cast(c[a] * c[a], ti.f64)
        self.sticking.evaluate(v, h, body_E, self.force, self.block)

    @ti.func
    def product_pass(self, z: ti.template(), p: ti.template(), beta, on):
        """product <- (the contact's Hessian) u, u = z + beta p (CG's next direction, as
        Elasticity.tet_stiffness takes it; beta = 0: u = z). on = 0: loops over nothing."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None] * on):
            self.product[i] = ti.Vector.zero(float, 3)
        ti.loop_config(serialize=self.serial_vertices)
        for k in range(self.close_count[None] * on):
            ids, c = self.close_ids[k], self.pair_weights[k]
            s = ti.Vector.zero(float, 3)
            for a in ti.static(range(4)):
                s += c[a] * (z[ids[a]] + beta * p[ids[a]])
            self.scatter(self.product, ids, c, self.pair_matrix[k] @ s)
        self.sticking.product(z, p, beta, on, self.product)

    # ------------------------------------------------------------ the step's passes

    @ti.kernel
    def find(self, x: ti.template()):
        """The pairs closer than d_hat at x (the step's start: its energy BEFORE)."""
        self.broad.near_pairs(x, self.distance[None])

    @ti.kernel
    def start(self, x: ti.template(), v: ti.template(), h: float, body_E: ti.template()):
        """At the step's first iterate x (= x_n): the lagged friction pairs (the touching ones,
        with their normal force), then E's terms and Hessian there (for the preconditioner)."""
        d_hat = self.distance[None]
        self.sticking.clear()
        ti.loop_config(serialize=self.serial_vertices)
        for q in range(self.pair_count[None]):
            ids, edge = self.vertices(q)
            d, n, c = self.gap(x, ids, edge)
            if d < d_hat:
                km = self.stiffness[None] * self.pair_mass(ids, edge)
                self.sticking.lag(self.pairs[q], c, n, km * barrier(d, d_hat)[1] * self.mollifier(x, ids, edge)[0])
        self.evaluate(x, v, h, body_E)            # (body_E is the energy pass's to fill: it starts it anew)

    @ti.kernel
    def clear_forces(self):
        """force <- 0: the pairs push nothing into a_n where the history is fresh (as the ground's deep
        vertices, Effects.release_deep): a body 1 mm into d_hat feels 3,000 m/s^2, which the step turns
        into a push, but a history started from it would carry into every later step."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.force[i] = ti.Vector.zero(float, 3)

    @ti.kernel
    def hold_start(self, x0: ti.template(), x: ti.template(), v: ti.template(), x_n: ti.template(), h: float):
        """Where the jump from x_n to the first iterate x (the integrator's guess) could bring a
        pair closer than (1 - SAFETY) of its gap, the first iterate is x_n itself (v = (x_n - x^) / h):
        every later iterate is reached by line searches that keep the pairs apart, so no step
        starts through a triangle. Leaves the pairs around x_n that the first iterate can meet."""
        self.largest_move[None] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for s in range(self.surface_count[None]):
            i = self.surface[s]
            self.broad.motion[i] = (x[i] - x_n[i]).norm()
            ti.atomic_max(self.largest_move[None], self.broad.motion[i])
        D = self.largest_move[None]
        self.broad.near_pairs(x_n, self.distance[None], ti.min(1.0, self.reach[None] / ti.max(D, 1e-30)))
        self.step_limit[None] = float(self.largest_move[None] <= self.reach[None])
        ti.loop_config(serialize=self.serial_vertices)
        for q in range(self.pair_count[None]):
            ids, edge = self.vertices(q)
            move = closing_bound(x[ids[0]] - x_n[ids[0]], x[ids[1]] - x_n[ids[1]],
                                 x[ids[2]] - x_n[ids[2]], x[ids[3]] - x_n[ids[3]], edge)
            if move > SAFETY * self.gap(x_n, ids, edge)[0]:
                self.step_limit[None] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None] * (self.step_limit[None] < 1.0)):
            u = self.effects.filtered(i, (x_n[i] - x0[i]) / h)
            v[i] = u
            x[i] = x0[i] + h * u

    @ti.kernel
    def prepare_search(self, x: ti.template(), d: ti.template(), h: float) -> float:
        """Before a line search from the accepted iterate x along d: the pairs it can meet (within
        d_hat + 2 D, D = h max_i |d_i|, capped at `reach`) and the largest step a <= 1 that keeps
        every pair at least (1 - SAFETY) of its gap apart; returns that step, and body_limit <- the
        largest for each body's own pairs (an island of bodies searches from the least of its own:
        one pair closing fast in a pile cut every other box's step short)."""
        self.largest_move[None] = 0.0
        ti.loop_config(serialize=self.serial_vertices)
        for s in range(self.surface_count[None]):
            i = self.surface[s]
            self.broad.motion[i] = h * d[i].norm()
            ti.atomic_max(self.largest_move[None], self.broad.motion[i])
        D, limit = self.largest_move[None], 1.0
        if D > self.reach[None]:
            limit = self.reach[None] / D
        self.broad.near_pairs(x, self.distance[None], limit)
        self.broad.find_islands()
        self.step_limit[None] = limit
        ti.loop_config(serialize=True)
        for b in range(self.model.body_count[None]):
            self.body_limit[b] = limit
        ti.loop_config(serialize=self.serial_vertices)
        for q in range(self.pair_count[None]):
            ids, edge = self.vertices(q)
            a = self.time_of_impact(x, d, h, ids, edge, limit)
            ti.atomic_min(self.step_limit[None], a)
            for k in ti.static(range(4)):
                ti.atomic_min(self.body_limit[self.model.vertex_body[ids[k]]], a)
        return self.step_limit[None]

    @ti.func
    def time_of_impact(self, x: ti.template(), d: ti.template(), h, ids, edge, limit):
        """The largest a <= limit along x + a h d that keeps the pair at least (1 - SAFETY) of its
        gap apart: additive CCD (Li et al. 2021). The four points move by h d less their mean, so
        the gap closes at most `move` a; the search advances by SAFETY gap(a) / move while the gap
        stays above (1 - SAFETY) of the first one. A pair that slides along its triangle, or moves
        with it, closes little and keeps the full step."""
        mean = 0.25 * (d[ids[0]] + d[ids[1]] + d[ids[2]] + d[ids[3]])
        u = ti.Vector.zero(float, 3, 4)
        for a in ti.static(range(4)):
            u[:, a] = h * (d[ids[a]] - mean)
        move = closing_bound(u[:, 0], u[:, 1], u[:, 2], u[:, 3], edge)
        gap0 = self.gap(x, ids, edge)[0]
        t, result = 0.0, limit
        if gap0 > TOUCHING and move * limit > SAFETY * gap0:
            gap = gap0
            for _ in range(ADVANCES):
                s = t + SAFETY * gap / move                   # the gap closes at most SAFETY of itself
                gap = points_gap(x[ids[0]] + s * u[:, 0], x[ids[1]] + s * u[:, 1],
                                 x[ids[2]] + s * u[:, 2], x[ids[3]] + s * u[:, 3], edge)[0]
                if t > 0 and gap < (1.0 - SAFETY) * gap0:     # as close as it may come: stop at t
                    break
                t = s
                if t >= limit:
                    break
            result = ti.min(t, limit)
        return result

    # ------------------------------------------------------------ for checks and tests

    @ti.kernel
    def terms(self, x: ti.template(), v: ti.template(), h: float, sums: ti.template()):
        """`evaluate` at (x, v) with the current pairs, each body's energies into sums (J)."""
        ti.loop_config(serialize=self.serial_vertices)
        for b in range(self.model.body_count[None]):
            sums[b] = 0.0
        self.evaluate(x, v, h, sums)

    @ti.kernel
    def apply(self, u: ti.template()):
        """product <- the Hessian of the last `evaluate` times u."""
        self.product_pass(u, u, 0.0, 1)

    @ti.kernel
    def find_within(self, x: ti.template(), radius: float, scale: float):
        """pairs <- every pair closer than radius + m_a + m_b at x, m = scale * broad.motion (BroadPhase.find_pairs)."""
        self.broad.near_pairs(x, radius, scale)

    @ti.func
    def share_energy(self, x: ti.template()):
        """energy <- each vertex's share of the contact energy at x (J, float64): half of a pair's
        to its vertex, half to its triangle's, by their weights."""
        ti.loop_config(serialize=self.serial_vertices)
        for i in range(self.model.vertex_count[None]):
            self.energy[i] = 0.0
        d_hat = self.distance[None]
        ti.loop_config(serialize=self.serial_vertices)
        for q in range(self.pair_count[None]):
            ids, edge = self.vertices(q)
            d, n, c = self.gap(x, ids, edge)
            if d < d_hat:
                km = ti.cast(self.stiffness[None] * self.pair_mass(ids, edge), ti.f64)
                e = 0.5 * km * barrier(d, d_hat)[0] * ti.cast(self.mollifier(x, ids, edge)[0], ti.f64)
                for a in ti.static(range(4)):                  # half to each side, by its weights
                    self.energy[ids[a]] += ti.abs(ti.cast(c[a], ti.f64)) * e

    @ti.kernel
    def measure(self, x: ti.template(), points: ti.types.ndarray()):
        """smallest <- the smallest pair distance at x (m; d_hat + 1 without pairs); touching <-
        the pairs closer than d_hat, the first rows of points (k, 3) the midpoints of their closest
        points (m); crossing <- those of two bodies whose vertex is behind its triangle (inside the
        other body's surface), interpenetrating. (Within one body a vertex behind its own surface
        is inside its own body: a plate squashed to d_hat has its top vertices that close behind
        its bottom triangles.)"""
        d_hat = self.distance[None]
        self.smallest[None], self.touching[None], self.crossing[None] = d_hat + 1.0, 0, 0
        ti.loop_config(serialize=self.serial_vertices)
        for q in range(self.pair_count[None]):
            ids, edge = self.vertices(q)
            d, n, c = self.gap(x, ids, edge)
            ti.atomic_min(self.smallest[None], d)
            if d < d_hat:
                k = ti.atomic_add(self.touching[None], 1)
                a, b, e = x[ids[1]], x[ids[2]], x[ids[3]]
                if k < points.shape[0]:                   # c[0] x0 + c[1] x1: the first side's point
                    for j in ti.static(range(3)):
                        points[k, j] = c[0] * x[ids[0]][j] + c[1] * x[ids[1]][j] * edge - 0.5 * (
                            c[0] * x[ids[0]][j] + c[1] * a[j] + c[2] * b[j] + c[3] * e[j])
                inside_face = c[1] < 0 and c[2] < 0 and c[3] < 0      # closest to the face, not an edge
                other = self.model.vertex_body[ids[0]] != self.model.vertex_body[ids[1]]
                if not edge and other and inside_face and (x[ids[0]] - a).dot((b - a).cross(e - a)) < 0:
                    self.crossing[None] += 1
