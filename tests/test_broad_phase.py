"""The broad phase of contact (fem/implicit/broad_phase.py) finds every pair closer than its radius and
nothing else, checked against numpy's distances of all surface vertex-triangle and edge-edge pairs; a
search that reuses a wider one's candidates (`near_pairs`) finds the same pairs while they are valid,
and searches again once the surface moved too far for them."""

import numpy as np
import pytest

import fem
import scenes
from fem.implicit.broad_phase import MARGIN


def point_segment(p, a, b):
    t = np.clip(np.dot(p - a, b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return np.linalg.norm(p - (a + t * (b - a)))


def segments(a0, a1, b0, b1):
    """numpy: the distance of two segments, the least of an interior stationary point (where both
    closest points are inside) and the four endpoint-to-segment distances."""
    best = min(point_segment(a0, b0, b1), point_segment(a1, b0, b1), point_segment(b0, a0, a1),
               point_segment(b1, a0, a1))
    u, w = a1 - a0, b1 - b0
    M = np.array([[u @ u, -u @ w], [-u @ w, w @ w]])
    if abs(np.linalg.det(M)) > 1e-12 * (u @ u) * (w @ w):
        s, t = np.linalg.solve(M, [-(a0 - b0) @ u, (a0 - b0) @ w])
        if 0 < s < 1 and 0 < t < 1:
            best = min(best, np.linalg.norm(a0 + s * u - b0 - t * w))
    return best


def point_triangle(p, a, b, c):
    """numpy: the distance from p to triangle (a, b, c): to its plane where the foot is inside, else to an edge."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    foot = p - np.dot(p - a, n) * n
    s, t = np.linalg.lstsq(np.column_stack([b - a, c - a]), foot - a, rcond=None)[0]
    if s >= 0 and t >= 0 and s + t <= 1:
        return abs(np.dot(p - a, n))
    return min(point_segment(p, a, b), point_segment(p, b, c), point_segment(p, c, a))


def every_pair(x, triangles, edges, radius, motion=None):
    """{(vertex, triangle)} and {(-e - 1, f), e < f} closer than radius + m_a + m_b, sharing no vertex (m the
    most any of a side's vertices moves, `motion` per vertex; none by default)."""
    near, surface = set(), np.unique(triangles)
    m = np.zeros(len(x)) if motion is None else motion
    largest = radius + 2 * m.max()
    for k, t in enumerate(triangles):             # (a vertex outside a triangle's box grown by radius is further)
        box = (x[t].min(0) - largest <= x[surface]).all(1) & (x[surface] <= x[t].max(0) + largest).all(1)
        near |= {(i, k) for i in surface[box]
                 if i not in t and point_triangle(x[i], *x[t]) < radius + m[i] + m[t].max()}
    for e, (a0, a1) in enumerate(edges):
        low, high = np.minimum(x[a0], x[a1]) - largest, np.maximum(x[a0], x[a1]) + largest
        for f in np.flatnonzero((np.maximum(x[edges[:, 0]], x[edges[:, 1]]) >= low).all(1) &
                                (np.minimum(x[edges[:, 0]], x[edges[:, 1]]) <= high).all(1)):
            b0, b1 = edges[f]
            reach = radius + m[[a0, a1]].max() + m[[b0, b1]].max()
            if f > e and len({a0, a1, b0, b1}) == 4 and segments(x[a0], x[a1], x[b0], x[b1]) < reach:
                near.add((-e - 1, int(f)))
    return near


def same(pairs, x, triangles, edges, radius, motion=None):
    """pairs are every pair closer than radius (+ m_a + m_b), up to those within 1e-9 m of it (round-off)."""
    return (every_pair(x, triangles, edges, radius - 1e-9, motion) <= pairs
            <= every_pair(x, triangles, edges, radius + 1e-9, motion))


def found(contact):
    return {tuple(int(k) for k in pair) for pair in contact.pairs.to_numpy()[:contact.pair_count[None]]}


@pytest.fixture(scope="module")
def boxes():
    """scenes/two_boxes.toml's upper box lowered to 1 cm above the lower one, a little askew."""
    fem.init("cpu", "f64")
    sim = fem.Simulation(scenes.load_scene("two_boxes"))
    x = sim.model.rest_positions_np.copy()
    upper = sim.model.bodies[1].vertices
    lowest, top = x[upper, 1].min(), x[sim.model.bodies[0].vertices, 1].max()
    x[upper] += (0.0, top + 0.01 - lowest, 0.0)
    x[upper] += 0.003 * np.random.default_rng(1).standard_normal(x[upper].shape)
    contact = sim.solver.effects.contact
    triangles = contact.triangles.to_numpy()[:contact.triangle_count[None]]
    edges = contact.edges.to_numpy()[:contact.edge_count[None]]
    yield sim, x, triangles, edges
    fem.init("cpu", "f32")


def search(sim, x, radius, motion=None):
    contact = sim.solver.effects.contact
    sim.model.write(sim.state.x, x)
    if motion is not None:
        sim.model.write(contact.broad.motion, motion)
    contact.find_within(sim.state.x, radius, 0.0 if motion is None else 1.0)
    assert contact.overflow[None] == 0
    return found(contact)


def test_the_pairs_found_are_every_pair_closer_than_the_radius(boxes):
    sim, x, triangles, edges = boxes
    sim.solver.effects.contact.broad.forget()
    pairs = search(sim, x, 0.02)
    assert len(pairs) > 50 and any(p[0] < 0 for p in pairs) and any(p[0] >= 0 for p in pairs)
    assert same(pairs, x, triangles, edges, 0.02)


def test_a_search_reuses_the_wider_one_while_it_holds_and_searches_again_after(boxes):
    sim, x, triangles, edges = boxes
    broad, d_hat = sim.solver.effects.contact.broad, float(sim.solver.effects.contact.distance[None])
    broad.forget()
    search(sim, x, 0.02)
    wider = float(broad.searched_radius[None])
    assert wider == pytest.approx(0.02 + 2 * MARGIN * d_hat)
    rng = np.random.default_rng(2)
    for _ in range(3):                        # each vertex moved less than the margin allows
        moved = x + 0.2 * MARGIN * d_hat * rng.uniform(-1, 1, x.shape) / np.sqrt(3)
        pairs = search(sim, moved, 0.015)
        assert float(broad.searched_radius[None]) == wider                    # the same candidates
        assert same(pairs, moved, triangles, edges, 0.015)
    far = x.copy()
    far[sim.model.bodies[1].vertices] -= (0.0, 1.5 * MARGIN * d_hat, 0.0)     # the upper box came closer
    pairs = search(sim, far, 0.015)
    assert float(broad.searched_radius[None]) != wider                        # searched again
    assert same(pairs, far, triangles, edges, 0.015)


def test_each_side_reaches_as_far_as_it_moves(boxes):
    """With motion, a pair is found where it is closer than the radius plus the most each side may move (the line
    search's bound on how far it can close): the upper box moving 3 cm finds its far pairs, the still box none."""
    sim, x, triangles, edges = boxes
    broad = sim.solver.effects.contact.broad
    motion = np.zeros(len(x))
    upper = np.arange(len(x))[sim.model.bodies[1].vertices]
    motion[upper] = 0.03 * np.random.default_rng(3).uniform(0.5, 1.0, len(upper))
    broad.forget()
    still = search(sim, x, 0.005)
    pairs = search(sim, x, 0.005, motion)
    assert len(pairs) > 2 * len(still)
    assert same(pairs, x, triangles, edges, 0.005, motion)
    rng = np.random.default_rng(4)
    for _ in range(2):                        # reused while each vertex moved less than its room, then not
        moved = x + 0.2 * MARGIN * 0.01 * rng.uniform(-1, 1, x.shape) / np.sqrt(3)
        pairs = search(sim, moved, 0.005, 0.5 * motion)
        assert same(pairs, moved, triangles, edges, 0.005, 0.5 * motion)
    pairs = search(sim, x, 0.005, 2.0 * motion)
    assert same(pairs, x, triangles, edges, 0.005, 2.0 * motion)
