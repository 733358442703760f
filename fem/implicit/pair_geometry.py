"""One contact pair's geometry and energy (fem/implicit/contact.py): its distance, normal and
weights (`points_gap`), how fast it can close (`closing_bound`), and IPC's barrier (`barrier`).

A pair is four points: a vertex p0 and a triangle (p1, p2, p3), or two edges (p0, p1) and
(p2, p3). Its weights c make r = sum_a c_a p_a the vector between its closest points, so that
grad_a d = c_a n: the force on each point is its weight times the pair's.
"""

import taichi as ti

from fem.implicit.broad_phase import closest_weights, segment_weights

TOUCHING = 1e-9              # m: pairs closer than this cannot be kept apart by a step bound


@ti.func
def barrier(d, d_hat):
    """IPC's log barrier (Li et al. 2020) of a pair at distance d < d_hat, per unit k m_p:
    b(d) = -(d_hat - d)^2 ln(d / d_hat), float64 (m^2); the push -b'(d) = e (e / d - 2 ln(d / d_hat)),
    e = d_hat - d (m); and the curvature b''(d) = 4 e / d + e^2 / d^2 - 2 ln(d / d_hat). It is 0 with
    its first two derivatives at d_hat and grows without bound as d -> 0, so no minimisation brings a
    pair together, however fast it comes (a penalty holds at most k m_p d_hat^2 / 2)."""
    d = ti.max(d, ti.static(TOUCHING))
    e, log = d_hat - d, ti.log(d / d_hat)
    phi = -ti.cast(e, ti.f64) ** 2 * ti.cast(log, ti.f64)
    return phi, e * (e / d - 2.0 * log), 4.0 * e / d + e * e / (d * d) - 2.0 * log


@ti.func
def points_gap(p0, p1, p2, p3, edge):
    """(d, n, weights c) of a pair: d = |r| and n = r / d, r = sum_a c_a p_a the vector between its
    closest points. A vertex p0 and a triangle (p1, p2, p3): c = (1, -w0, -w1, -w2), w the
    closest point's barycentric weights; edges (p0, p1) and (p2, p3): c = (1 - s, s, -(1 - t), -t).
    Touching (d <= TOUCHING), n is the triangle's normal or the edges' cross product."""
    c = ti.Vector([0.0, 0.0, 0.0, 0.0])
    n = ti.Vector([0.0, 0.0, 0.0])
    if edge:
        s, t = segment_weights(p0, p1, p2, p3)
        c = ti.Vector([1.0 - s, s, t - 1.0, -t])
        n = (p1 - p0).cross(p3 - p2)
    else:
        w = closest_weights(p0, p1, p2, p3)
        c = ti.Vector([1.0, -w[0], -w[1], -w[2]])
        n = (p2 - p1).cross(p3 - p1)
    r = c[0] * p0 + c[1] * p1 + c[2] * p2 + c[3] * p3
    d = r.norm()
    n = n / ti.max(n.norm(), 1e-30)
    if d > TOUCHING:
        n = r / d
    return d, n, c


@ti.func
def closing_bound(u0, u1, u2, u3, edge):
    """The most a pair's gap can change when its points move by u0..u3: |u0| + max(|u1|, |u2|, |u3|)
    (a vertex and a triangle), max(|u0|, |u1|) + max(|u2|, |u3|) (two edges)."""
    bound = u0.norm() + ti.max(u1.norm(), u2.norm(), u3.norm())
    if edge:
        bound = ti.max(u0.norm(), u1.norm()) + ti.max(u2.norm(), u3.norm())
    return bound
