"""Contact between bodies and within one (fem/implicit/contact.py): the pairs' penalty is an
energy of the step, so it has an exact gradient and a PSD Hessian; no step ends with one body
inside another (checked with numpy, point in tet, independently of the contact code); the
total energy never rises; with contact off nothing changes."""

import numpy as np
import pytest
import taichi as ti
from scipy.optimize import minimize

import fem
import scenes
from fem.implicit.contact import MOLLIFIER
from fem.scene import Body, ContactEffect, Effects, Impulse, Material, Scene, Selection, SolverSettings
from scenes.hard_cases import cube


def box(cells, size, position, name):
    mesh = cube(cells=cells, size=size)
    return Body(name, type(mesh)(mesh.vertices + np.asarray(position), mesh.tets, mesh.source),
                Material(1e4, 0.3, 1000.0), "corotational")


def two_boxes(gap, distance=0.05, friction=0.0, dt=0.01):
    """A box of 0.5 m over a box of 1 m whose top is at y = 0, `gap` apart (m), no gravity."""
    lower = box(2, (1.0, 1.0, 1.0), (0.0, -0.5, 0.0), "lower")
    upper = box(1, (0.5, 0.5, 0.5), (0.1, gap + 0.25, -0.05), "upper")
    return Scene("two", [lower, upper], effects=Effects(contact=ContactEffect(distance, friction)),
                 solver=SolverSettings(dt=dt))


def two_boxes_at(gap, **kwargs):
    """A Simulation of `two_boxes` with the boxes `gap` apart, closer than the contact distance
    where a test needs pairs inside it: a scene that starts there is refused (fem/contact_start.py),
    so it is built 0.1 m apart and its upper box moved down by set_state."""
    built = max(gap, 0.1)
    sim = fem.Simulation(two_boxes(built, **kwargs))
    x = sim.positions()
    x[sim.model.bodies[1].vertices, 1] -= built - gap
    sim.set_state(x, sim.velocities())
    return sim


# ------------------------------------------------------------ an independent check: point in tet

def points_inside(x, tets, points, tol=1e-9):
    """How many of points (k, 3) lie strictly inside some tet (m, 4) of positions x (n, 3)."""
    P = x[tets]
    edges = np.stack([P[:, 0] - P[:, 3], P[:, 1] - P[:, 3], P[:, 2] - P[:, 3]], axis=2)
    inverse = np.linalg.inv(edges)
    lo, hi = P.min(axis=1), P.max(axis=1)
    count = 0
    for p in points:
        near = np.where(((p >= lo) & (p <= hi)).all(axis=1))[0]
        b = np.einsum("mij,mj->mi", inverse[near], p - P[near, 3])
        b = np.concatenate([b, 1.0 - b.sum(axis=1, keepdims=True)], axis=1)
        count += bool((b.min(axis=1) > tol).any())
    return count


def winding(points, x, triangles):
    """The generalised winding number of a closed, outward triangle surface at each point (k, 3):
    1 inside, 0 outside (Jacobson et al. 2013: the solid angles summed, Van Oosterom's formula)."""
    a, b, c = (x[triangles[:, k]][None] - points[:, None] for k in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=2) for v in (a, b, c))
    dot = lambda u, v: np.einsum("pti,pti->pt", u, v)
    angle = np.arctan2(dot(a, np.cross(b, c)), la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb)
    return angle.sum(axis=1) / (2 * np.pi)


def edges_through(x, edges, triangles, apart=True):
    """How many of segments (e, 2) pass through the inside of triangles (t, 3) (Moller-Trumbore),
    of the pairs where apart (e, t) is true."""
    p, d = x[edges[:, 0]][:, None], (x[edges[:, 1]] - x[edges[:, 0]])[:, None]
    a, e1, e2 = (x[triangles[:, 0]][None], (x[triangles[:, 1]] - x[triangles[:, 0]])[None],
                 (x[triangles[:, 2]] - x[triangles[:, 0]])[None])
    dot = lambda u, v: np.einsum("eti,eti->et", u, v)
    pv = np.cross(d, e2)
    det = dot(np.broadcast_to(e1, pv.shape), pv)
    inverse = np.divide(1.0, det, out=np.zeros_like(det), where=np.abs(det) > 1e-300)
    s = p - a
    qv = np.cross(s, np.broadcast_to(e1, s.shape))
    u, v = dot(s, pv) * inverse, dot(np.broadcast_to(d, qv.shape), qv) * inverse
    t = dot(np.broadcast_to(e2, qv.shape), qv) * inverse
    return int(((u > 0) & (v > 0) & (u + v < 1) & (t > 0) & (t < 1) & (det != 0) & apart).sum())


def overlaps(sim):
    """Where surfaces overlap, summed over ordered pairs of bodies: surface vertices of one inside
    the other's closed surface (winding number), and surface edges of one through the other's
    triangles; and within each body, its surface edges through its triangles that share no vertex
    with them (a body folded through itself). Surfaces, not tets: a tet turned inside out by an
    impact covers points outside its body."""
    m = sim.model
    x = sim.state.x.to_numpy()[:m.n_vertices].astype(np.float64)
    triangles = m.surface
    stops = [b.vertices.stop for b in m.bodies]
    owner = np.searchsorted(stops, triangles[:, 0], side="right")
    edges = np.unique(np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]),
                              axis=1), axis=0)
    edge_owner = np.searchsorted(stops, edges[:, 0], side="right")
    count = 0
    for a in range(len(m.bodies)):
        points = x[np.unique(triangles[owner == a])]
        for b in range(len(m.bodies)):
            if b != a:
                count += int((winding(points, x, triangles[owner == b]) > 0.5).sum())
                count += edges_through(x, edges[edge_owner == a], triangles[owner == b])
        own, own_edges = triangles[owner == a], edges[edge_owner == a]
        apart = ~(own_edges[:, None, :, None] == own[None, :, None, :]).any(axis=(2, 3))
        count += edges_through(x, own_edges, own, apart)
    return count


def point_triangle_distance(p, a, b, c):
    """numpy: distance and closest point, by projection onto the plane or else the nearest edge."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    q = p - np.dot(p - a, n) * n
    M = np.column_stack([b - a, c - a])
    s, t = np.linalg.lstsq(M, q - a, rcond=None)[0]
    if s >= 0 and t >= 0 and s + t <= 1:
        return np.linalg.norm(p - q), q
    best = None
    for u, w in ((a, b), (b, c), (c, a)):
        r = np.clip(np.dot(p - u, w - u) / np.dot(w - u, w - u), 0.0, 1.0)
        e = u + r * (w - u)
        if best is None or np.linalg.norm(p - e) < best[0]:
            best = (np.linalg.norm(p - e), e)
    return best


# ------------------------------------------------------------ energy, gradient, Hessian

def contact_terms(sim, x, h=1.0):
    """(E, -h grad E (n, 3), the contact part) at positions x (n, 3), pairs found within 0.2 m."""
    contact = sim.solver.effects.contact
    field = sim.solver.potential.x
    sim.model.write(field, x)
    sums = ti.field(ti.f64, len(sim.model.bodies))
    contact.terms(field, sim.solver.potential.v, h, sums)
    return sums.to_numpy().sum(), contact.force.to_numpy()[:sim.model.n_vertices].astype(np.float64)


def test_the_contact_gradient_is_the_energy_s_and_its_hessian_is_symmetric_and_psd(f64):
    sim = two_boxes_at(0.02)
    contact, m = sim.solver.effects.contact, sim.model
    x = sim.state.x.to_numpy()[:m.n_vertices].astype(np.float64)
    upper = x[m.bodies[1].vertices]
    turn = np.array([[np.cos(0.02), 0, np.sin(0.02)], [0, 1, 0], [-np.sin(0.02), 0, np.cos(0.02)]])
    centre = upper.mean(axis=0)
    # off the grid (no ties), and turned 0.02 rad about y: the boxes' edges nearly parallel, where
    # IPC's mollifier fades their pairs (sin^2 = 4e-4 < MOLLIFIER)
    x[m.bodies[1].vertices] = (upper - centre) @ turn.T + centre + np.array([0.163, -0.004, 0.021])
    sim.model.write(sim.solver.potential.x, x)
    contact.find_within(sim.solver.potential.x, 0.2, 0.0)
    assert contact.pair_count[None] > 0
    E, force = contact_terms(sim, x)
    assert E > 0
    rng = np.random.default_rng(1)
    for _ in range(5):                                  # directional derivatives, central differences
        u = rng.standard_normal(x.shape)
        eps = 1e-6
        slope = (contact_terms(sim, x + eps * u)[0] - contact_terms(sim, x - eps * u)[0]) / (2 * eps)
        assert slope == pytest.approx(-(force * u).sum(), rel=1e-6, abs=1e-9 * E)
    # the numbers themselves, from numpy: IPC's barrier E = sum -k m_p (d_hat - d)^2 ln(d / d_hat) over
    # pairs closer than d_hat (times the mollifier on edges), and Gauss-Newton's Hessian k m_p b''(d) g g^T
    k = contact.stiffness[None]
    d_hat = contact.distance[None]
    pairs = contact.pairs.to_numpy()[:contact.pair_count[None]]
    triangles, edges = contact.triangles.to_numpy(), contact.edges.to_numpy()
    assert (pairs[:, 0] < 0).any() and (pairs[:, 0] >= 0).any()       # edge-edge pairs and vertex-triangle ones
    expected, H, mollified = 0.0, np.zeros((3 * m.n_vertices,) * 2), 0
    for p, t in pairs:
        if p >= 0:                                      # a vertex and a triangle
            d, c = point_triangle_distance(x[p], *x[triangles[t]])
            a, b, e = x[triangles[t]]
            s, r = np.linalg.lstsq(np.column_stack([b - a, e - a]), c - a, rcond=None)[0]
            corners, weights, mass = [p, *triangles[t]], [1.0, s + r - 1.0, -s, -r], m.mass_np[p]
        else:                                           # two edges: their closest points by scipy
            corners = [*edges[-p - 1], *edges[t]]
            a0, a1, b0, b1 = x[corners]
            gap = lambda st: np.linalg.norm(a0 + st[0] * (a1 - a0) - b0 - st[1] * (b1 - b0))
            best = min((minimize(gap, start, bounds=[(0, 1), (0, 1)], method="L-BFGS-B",
                                 options={"ftol": 1e-15, "gtol": 1e-12})
                        for start in ([0.5, 0.5], [0.1, 0.9], [0.9, 0.1])), key=lambda result: result.fun)
            s, r = best.x
            d, weights, mass = best.fun, [1.0 - s, s, r - 1.0, -r], m.mass_np[corners].mean()
            rest = m.rest_positions_np[corners]
            eps = MOLLIFIER * np.sum((rest[1] - rest[0]) ** 2) * np.sum((rest[3] - rest[2]) ** 2)
            y = np.sum(np.cross(a1 - a0, b1 - b0) ** 2)
            mass *= (2 - y / eps) * y / eps if y < eps else 1.0          # IPC's mollifier, in the stiffness
            mollified += bool(0 < y < eps and d < d_hat)
        if d < d_hat:
            expected += -k * mass * (d_hat - d) ** 2 * np.log(d / d_hat)
            n = sum(w * x[v] for v, w in zip(corners, weights)) / d
            curvature = 4 * (d_hat - d) / d + ((d_hat - d) / d) ** 2 - 2 * np.log(d / d_hat)
            g = np.zeros(3 * m.n_vertices)
            for vertex, weight in zip(corners, weights):
                g[3 * vertex:3 * vertex + 3] += weight * n
            H += k * mass * curvature * np.outer(g, g)
    assert E == pytest.approx(expected, rel=1e-9)
    assert mollified > 0
    contact_terms(sim, x)                               # the Hessian at x (the last evaluation's)
    for _ in range(3):                                  # H u: numpy's Gauss-Newton matrix, symmetric, PSD
        u = rng.standard_normal(x.shape)
        sim.model.write(sim.solver.linear.p, u)
        contact.apply(sim.solver.linear.p)
        Hu = contact.product.to_numpy()[:m.n_vertices].astype(np.float64).ravel()
        # (scipy finds the closest points of nearly parallel edges, where they are ill-conditioned, to 1e-7)
        np.testing.assert_allclose(Hu, H @ u.ravel(), rtol=1e-6, atol=1e-6 * np.abs(H @ u.ravel()).max())
    assert np.linalg.eigvalsh(H).min() > -1e-9 * np.abs(H).max()


# ------------------------------------------------------------ the line search's step bound (additive CCD)

def smallest_gap(x, sim):
    """numpy: the smallest distance from a surface vertex of one box to a surface triangle of the other."""
    contact, m = sim.solver.effects.contact, sim.model
    triangles = contact.triangles.to_numpy()[:contact.triangle_count[None]]
    body = m.vertex_body_np[:m.n_vertices]
    surface = np.unique(triangles)
    return min(point_triangle_distance(x[p], *x[t])[0]
               for p in surface for t in triangles if body[t[0]] != body[p])


@pytest.mark.parametrize("motion, full", [("slide", True), ("turn", True), ("approach", False)])
def test_the_step_bound_keeps_the_pairs_apart_and_lets_a_slide_take_its_full_step(f64, motion, full):
    """Contact.prepare_search along a direction that moves the upper box 5 times its 2 cm gap: sliding
    across the lower box or turning on it, no pair closes, and the step is the full one (a bound
    from how far the points move, and not where, gave 0.18); coming straight down, the step stops
    the box before it reaches the other, a tenth of the gap apart (numpy's distances, not the
    contact code's), and no earlier than the straight line allows (0.9 of 0.02 m over 0.1 m)."""
    sim = two_boxes_at(0.02)
    contact, m = sim.solver.effects.contact, sim.model
    x = sim.state.x.to_numpy()[:m.n_vertices].astype(np.float64)
    upper = m.bodies[1].vertices
    centre = x[upper].mean(axis=0)
    d = np.zeros_like(x)
    if motion == "slide":
        d[upper] = [0.1, 0.0, 0.0]
    elif motion == "turn":                              # about the vertical axis, 0.1 m at the corners
        r = x[upper] - centre
        d[upper] = 0.1 / np.linalg.norm(r[:, [0, 2]], axis=1).max() * np.stack([-r[:, 2], 0 * r[:, 0], r[:, 0]], axis=1)
    else:
        d[upper] = [0.0, -0.1, 0.0]
    sim.model.write(sim.solver.potential.x, x)
    sim.model.write(sim.solver.linear.p, d)
    a = contact.prepare_search(sim.solver.potential.x, sim.solver.linear.p, 1.0)
    gap = smallest_gap(x, sim)
    if full:
        assert a == 1.0
    else:
        assert 0.17 <= a < 0.2
    assert smallest_gap(x + a * d, sim) >= 0.1 * gap * (1 - 1e-9)


def test_a_box_sliding_on_another_slows_at_mu_g_and_every_step_converges(f64):
    """Coulomb friction between bodies: a 0.4 m box resting on a long one (on the ground) is pushed
    to 2 m/s; it slows at mu g (analytic: 1.12 m/s after 0.3 s at mu 0.3), the lower box holds
    (the ground's friction, 0.5, is the larger), and every step's Newton iteration converges, from
    settling to sliding. Newton's own model of friction sends a sliding pair that should stop far
    past rest: before the first iterations took its majorizer, settling steps ran to max_newton."""
    lower = box(2, (2.0, 0.4, 1.0), (0.0, 0.2, 0.0), "lower")
    upper = box(2, (0.4, 0.4, 0.4), (-0.5, 0.615, 0.0), "upper")      # 15 mm above: it lands first
    for body in (lower, upper):
        body.material = Material(1e6, 0.3, 1000.0)
    sim = fem.Simulation(Scene("slide", [lower, upper], solver=SolverSettings(dt=0.01),
                               effects=Effects(gravity=(0.0, -9.81, 0.0), ground=0.0, friction=0.5,
                                               contact=ContactEffect(0.01, 0.3))))
    rows = [sim.step() for _ in range(30)]
    v = sim.velocities()
    top = sim.model.bodies[1].vertices
    v[top, 0] += 2.0
    sim.set_state(sim.positions(), v)
    rows += [sim.step() for _ in range(30)]
    # the first step, in free fall 15 mm above, takes a rigid step instead of its solve's (the
    # residual's rise, which its deformation cannot pay for: docs/method.md, section 6), and says
    # it did not converge; every step after it converges, landing, settling and sliding
    assert rows[0]["energy_limited"] == 1 and not rows[0]["converged"]
    assert all(row["converged"] for row in rows[1:])
    assert sim.velocities()[top, 0].mean() == pytest.approx(2.0 - 0.3 * 9.81 * 0.3, rel=0.03)
    assert abs(sim.velocities()[sim.model.bodies[0].vertices, 0].mean()) < 0.01


# ------------------------------------------------------------ the two boxes

STEPS = 175


@pytest.fixture(scope="module")
def two_box_run():
    """The issue's scene (scenes/two_boxes.toml): a 0.6 m box dropped from 1.2 m onto a 1 m box
    on the ground, 3.5 s at dt 0.02 s in f32. Per step: overlaps, total energy and the stats row."""
    fem.init("cpu", "f32")
    sim = fem.Simulation(scenes.load_scene("two_boxes"))
    history = {"overlaps": [], "energy": [], "rows": []}
    history["energy"].append(sim.stats()["total_energy"])
    for _ in range(STEPS):
        history["rows"].append(sim.step())
        history["overlaps"].append(overlaps(sim))
        history["energy"].append(sim.stats()["total_energy"])
    history["x"] = sim.state.x.to_numpy()[:sim.model.n_vertices].astype(np.float64)
    history["v"] = sim.state.v.to_numpy()[:sim.model.n_vertices].astype(np.float64)
    history["bodies"], history["record"] = sim.model.bodies, sim.contact_record
    return history


def test_no_step_of_the_two_boxes_ends_with_a_vertex_inside_the_other_box(two_box_run):
    assert two_box_run["overlaps"] == [0] * STEPS
    assert all(row["finite"] for row in two_box_run["rows"])
    assert all(row["interpenetrating"] == 0 for row in two_box_run["rows"])
    assert two_box_run["record"]["most_pairs"] > 0                     # they did touch


def test_in_the_end_the_upper_box_rests_on_the_lower_one(two_box_run):
    """The issue's acceptance: the upper box (0.6 m) lands at 3.7 m/s on the lower one (0.5 m,
    on the ground), bounces a few times, lower each time (the boxes are undamped: BDF2 and friction
    take the energy), and from about 3 s on sits on it, in contact, centred, its centre 0.3 m above
    the lower box's 0.5 m (both soft, E = 1e5 Pa: they squash and ring by centimetres). Newton's
    steps stopping unconverged took energy too, and it rested by 1.6 s."""
    x, (lower, upper) = two_box_run["x"], two_box_run["bodies"]
    last = two_box_run["rows"][-35:]
    assert sum(row["contact_pairs"] > 0 for row in last) >= 0.6 * len(last)     # it still hops a little
    centre = x[upper.vertices].mean(axis=0)
    assert centre[1] - x[lower.vertices][:, 1].min() == pytest.approx(0.8, abs=0.06)
    assert np.abs(centre[[0, 2]]).max() < 0.1                           # over the middle
    assert np.abs(two_box_run["v"][upper.vertices].mean(axis=0)).max() < 1.0      # m/s, from 3.7


def test_total_energy_never_rises_through_the_impact(two_box_run):
    """Kinetic + elastic + gravitational + ground + contact energy, step to step, within the
    energy promise's f32 tolerance (scenes/hard_cases.py, ENERGY_TOLERANCE)."""
    energy = np.array(two_box_run["energy"])
    assert np.isfinite(energy).all()
    assert np.diff(energy).max() <= 1e-3 * np.abs(energy).max()
    assert energy[-1] < energy[0]                                       # the impact dissipated some


# ------------------------------------------------------------ one body meets itself

FOLD = """
name = "fold"
description = "A soft bar, its left half held, its right half swung up and over onto it."
[solver]
dt = 0.02
[effects]
gravity = [0.0, -9.81, 0.0]
contact = { distance = 0.01 }
[[body]]
name = "bar"
mesh = { generator = "box", size = [2.0, 0.2, 0.2], cells = [10, 1, 1] }
material = { E = 2e4, nu = 0.3, density = 300.0 }
pin = { box = { min = [-1.1, -1.0, -1.0], max = [-0.05, 1.0, 1.0] } }
[[initial]]
box = { min = [0.15, -1.0, -1.0], max = [1.1, 1.0, 1.0] }
spin = { axis = [0.0, 0.0, 1.0], omega = 9.0 }
[[initial]]
box = { min = [0.15, -1.0, -1.0], max = [1.1, 1.0, 1.0] }
velocity = [0.0, 5.4, 0.0]
"""


def test_a_bar_folding_onto_itself_does_not_pass_through_itself(f32, tmp_path):
    """Self-contact: the bar's free half swings up about the middle, over, and down onto its
    held half. No surface vertex of the free half ever lies inside the held half's tets."""
    path = tmp_path / "fold.toml"
    path.write_text(FOLD)
    sim = fem.Simulation(scenes.load_scene(path))
    m = sim.model
    rest = m.rest_positions_np
    held, free = np.where(rest[:, 0] < -0.05)[0], np.where(rest[:, 0] > 0.25)[0]
    held_tets = m.tets_np[np.isin(m.tets_np, held).all(axis=1)]
    surface = np.intersect1d(np.unique(m.surface), free)
    touched, furthest = 0, 1.0
    for _ in range(40):
        row = sim.step()
        assert row["finite"]
        x = sim.state.x.to_numpy()[:m.n_vertices].astype(np.float64)
        assert points_inside(x, held_tets, x[surface]) == 0
        touched = max(touched, row["contact_pairs"])
        furthest = min(furthest, x[free][:, 0].max())
    assert furthest < -0.3                  # m: the free half folded over, its end above the held half
    assert touched > 0


def test_a_sleeping_body_hit_wakes_and_takes_the_momentum(f64):
    """Two boxes in space fall asleep; at 0.6 s one is thrown at 5 m/s at the other. The one hit
    wakes before the step that reaches it (a body asleep is held like a pinned one: it would
    throw the other back), and the pair's total momentum is kept through the impact."""
    lower = box(1, (0.4, 0.4, 0.4), (0.0, 0.0, 0.0), "resting")
    thrown = box(1, (0.4, 0.4, 0.4), (-1.0, 0.02, 0.0), "thrown")
    scene = Scene("hit", [lower, thrown], effects=Effects(contact=ContactEffect(0.01, 0.0)),
                  solver=SolverSettings(dt=0.02),
                  impulses=[Impulse(0.6, Selection(1), np.array([5.0, 0.0, 0.0]))])
    sim = fem.Simulation(scene)
    m, masses = sim.model, sim.model.mass_np
    while sim.t < 0.59:
        sim.step()
    assert sim.asleep == [True, True]
    asleep_before, momentum = [], []
    while sim.t < 1.0:
        asleep_before.append(sim.asleep[0])
        sim.step()
        v = sim.velocities()
        momentum.append([(masses[b.vertices, None] * v[b.vertices]).sum(axis=0)[0] for b in m.bodies])
        assert overlaps(sim) == 0
    momentum = np.array(momentum)
    assert not all(asleep_before[1:]) and not sim.asleep[0]
    assert momentum[-1, 0] > 0.5 * momentum[0, 1]                   # the one hit moves on
    assert abs(momentum[-1].sum() - momentum[0].sum()) < 0.01 * momentum[0].sum()


# ------------------------------------------------------------ switched off, and bad input

def test_contact_off_compiles_no_contact_kernel(f32):
    """A scene without [effects] contact makes no Contact part: nothing of it is compiled."""
    scene = two_boxes(gap=0.5)
    scene.effects.contact = None
    sim = fem.Simulation(scene)
    sim.step()
    assert sim.solver.effects.contact is None and not sim.solver.switches.contact
    assert "contact_pairs" not in sim.last


@pytest.mark.parametrize("value, message", [("-0.01", "distance"), ("0.0", "distance"),
                                            ("nan", "distance")])
def test_a_bad_contact_distance_is_one_error_line(tmp_path, value, message):
    import subprocess
    import sys
    from pathlib import Path
    scene = (Path(scenes.__file__).parent / "two_boxes.toml").read_text().replace(
        "distance = 0.01", f"distance = {value}")
    path = tmp_path / "bad.toml"
    path.write_text(scene)
    out = subprocess.run([sys.executable, "main.py", "simulate", str(path), "--steps", "1"],
                         capture_output=True, text=True, cwd=Path(scenes.__file__).parents[1])
    assert out.returncode == 2
    assert out.stderr.strip().startswith("error:") and message in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1


def test_the_block_preconditioner_follows_the_pairs_touching_now(f64):
    """PCG's block-Jacobi blocks include the pairs' blocks of the Newton iteration that uses them, so
    preconditioning makes H better conditioned, not worse. Built once at the step's start, they
    missed the pairs that touched later and kept those that let go: on the scene two_boxes, in
    contact, cond(P H) was 152,000 against cond(H) 3,740 (numpy, from the assembled operators), and
    every step ran PCG to its cap."""
    sim = fem.Simulation(scenes.load_scene("two_boxes"))
    while sim.stats().get("contact_pairs", 0) == 0 or sim.steps < 22:
        sim.step()
        assert sim.steps < 60
    n = sim.model.n_vertices
    cM, cK = sim.coefficients
    sim.solver.linear.preconditioning.build_preconditioner(cM, cK)    # as Newton does before each solve
    H, P = np.zeros((3 * n, 3 * n)), np.zeros((3 * n, 3 * n))
    for j in range(3 * n):
        u = np.zeros((n, 3))
        u.flat[j] = 1.0
        H[:, j] = sim.solver.linear.apply_matrix(u, cM, cK).ravel()
        P[:, j] = sim.solver.linear.apply_preconditioner(u, "jacobi").ravel()
    np.testing.assert_allclose(H, H.T, atol=1e-5 * np.abs(H).max())     # symmetric (to f32's rounding)
    w, V = np.linalg.eigh(P)
    assert w.min() > 0                                          # SPD
    root = V @ np.diag(np.sqrt(w)) @ V.T
    preconditioned = np.linalg.eigvalsh(root @ H @ root)
    plain = np.linalg.eigvalsh(H)
    assert preconditioned.max() / preconditioned.min() < plain.max() / plain.min()
