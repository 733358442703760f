"""Starts that contact cannot take, refused before any work (numpy and scipy: no kernel compiled).

With contact on (fem/implicit/contact.py), the barrier keeps apart surfaces that start apart by
more than the contact distance d_hat. It cannot separate surfaces that start crossing or one body
inside another (they freeze in place, 1e5 J of barrier and more), it throws apart surfaces that
start closer than d_hat (a first step that gains energy), and a d_hat as thick as a body pushes
across the whole body. `check_start` refuses each of these with one FemError naming the scene,
the bodies and the depth (`separation`: how far one must move to clear the other) or gap in mm:

    1. the proportion: d_hat over a quarter of a body's thickness (its thinnest extent along its
       principal axes);
    2. crossing surfaces: a surface edge through a surface triangle of another body, or of the same
       body where they share no vertex (a body made of two overlapping cubes in one mesh);
    3. one body inside another: a vertex of its surface inside the other's surface (ray parity);
    4. gaps below d_hat: the smallest vertex-triangle and edge-edge distances between bodies.

A body of several connected pieces (two cubes in one mesh) is checked piece by piece, as contact
treats it. Candidate pairs come from k-d trees with radii that cannot miss one (scipy's cKDTree);
each candidate is then tested exactly.
"""

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from fem.errors import FemError

PROPORTION = 0.25            # d_hat may be at most this share of the thinnest body
# A direction for the point-in-surface rays that no face of an axis-aligned or 45-degree mesh is
# parallel to, so that a ray meets an edge or a corner only by a measure-zero accident.
RAY = np.array([0.5773, 0.6771, 0.4563]) / np.linalg.norm([0.5773, 0.6771, 0.4563])
# An edge crosses a triangle's plane only where both its ends are further from it than this share of
# the coordinates (m per m): closer is round-off of faces that touch, which check_gaps refuses as such.
ROUNDING = 1e-12
CHUNK = 1 << 20              # ray-triangle tests per numpy batch: a bounded memory on large meshes


def check_start(scene, x, bodies, tets):
    """FemError for a start with contact on that contact cannot take (the module's docstring):
    scene a fem.scene.Scene; x (n, 3) its start positions (m); bodies and tets (m, 4) global
    vertex ids, as fem.builder.model_arrays makes them. A scene without contact passes: bodies
    go through each other by design there."""
    if scene.effects.contact is None:
        return
    where, d_hat = scene.path or scene.name, scene.effects.contact.distance
    check_proportion(where, d_hat, [b.name for b in bodies], [x[b.vertices] for b in bodies])
    s = Surfaces(x, bodies, tets)
    check_crossings(where, s)
    check_nesting(where, s)
    check_gaps(where, s, d_hat)


def mm(metres):
    """'350 mm', '0.003 mm'."""
    return f"{metres * 1e3:.3g} mm"


def check_proportion(where, d_hat, names, positions):
    """d_hat over PROPORTION of a body's thinnest extent along its principal axes: refused."""
    for name, x in zip(names, positions):
        centred = x - x.mean(axis=0)
        axes = np.linalg.eigh(centred.T @ centred)[1]
        thickness = float(np.ptp(centred @ axes, axis=0).min())
        if d_hat > PROPORTION * thickness:
            raise FemError(f"{where}: the contact distance {mm(d_hat)} is over a quarter of body \"{name}\"'s "
                           f"thickness ({mm(thickness)}): contact would push across the whole body; "
                           f"use a contact distance of at most {mm(PROPORTION * thickness)}")


class Surfaces:
    """Every body's surface at the start, in one set of arrays.

    x (n, 3) positions, m; triangles (t, 3) and edges (e, 2) global vertex ids; piece (n,) the
    connected piece of its body each vertex is in, numbered over the scene; piece_body (p,) the
    body of each piece; names (bodies,)."""

    def __init__(self, x, bodies, tets):
        self.x, self.names = x, [b.name for b in bodies]
        links = np.concatenate([tets[:, [0, a]] for a in (1, 2, 3)])
        graph = coo_matrix((np.ones(len(links)), (links[:, 0], links[:, 1])), shape=(len(x), len(x)))
        count, self.piece = connected_components(graph, directed=False)      # no link joins two bodies
        first = np.unique(self.piece, return_index=True)[1]
        self.piece_body = np.searchsorted([b.vertices.start for b in bodies], first, side="right") - 1
        self.triangles = np.concatenate([b.surface for b in bodies]).astype(np.int64)
        sides = np.sort(self.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        keys = np.unique(sides[:, 0] * len(x) + sides[:, 1])          # each edge once
        self.edges = np.stack([keys // len(x), keys % len(x)], axis=1)
        self.triangle_piece = self.piece[self.triangles[:, 0]]
        corners = self.x[self.triangles].reshape(-1, 3)
        owner = np.repeat(self.triangle_piece, 3)
        self.lo, self.hi = np.full((count, 3), np.inf), np.full((count, 3), -np.inf)
        np.minimum.at(self.lo, owner, corners)
        np.maximum.at(self.hi, owner, corners)

    def between(self, a, b):
        """'bodies "a" and "b"', or 'two pieces of body "a"' for pieces a, b of one body."""
        first, second = self.names[self.piece_body[a]], self.names[self.piece_body[b]]
        if self.piece_body[a] == self.piece_body[b]:
            return f"two pieces of body \"{first}\""
        return f"bodies \"{first}\" and \"{second}\""


# ---------------------------------------------------------------- the checks

def check_crossings(where, s):
    """Surfaces that cross: refused with how far they overlap (`separation`)."""
    edges, triangles = crossings(s)
    if not len(edges):
        return
    a, b = s.piece[s.edges[edges, 0]], s.triangle_piece[triangles]
    if (a == b).any():            # one piece's surface through itself: no two sides to part
        k = np.flatnonzero(a == b)[0]
        at = ", ".join(f"{c:.3g}" for c in s.x[s.edges[edges[k]]].mean(axis=0))
        raise FemError(f"{where}: body \"{s.names[s.piece_body[a[k]]]}\"'s surface crosses itself near "
                       f"({at}) m: its surface must not cut through itself; check its mesh")
    pairs = np.unique(np.sort(np.stack([a, b], axis=1), axis=1), axis=0)
    moves = [separation(s, p, q) for p, q in pairs]
    k = max(range(len(pairs)), key=lambda k: moves[k][0])
    others = f" (and {len(pairs) - 1} more pairs)" if len(pairs) > 1 else ""
    raise FemError(f"{where}: {s.between(*pairs[k])} start overlapping, by {mm(moves[k][0])} along "
                   f"{moves[k][1]}{others}; contact cannot separate surfaces that start crossing: move them apart")


def check_nesting(where, s):
    """A piece entirely inside another (their surfaces do not cross, or check_crossings would have
    refused): one of its vertices is inside the other's surface."""
    around = ((s.lo[None] <= s.lo[:, None]) & (s.hi[:, None] <= s.hi[None])).all(axis=2)
    np.fill_diagonal(around, False)
    around[np.isinf(s.lo[:, 0])] = False               # a piece of no surface: lone vertices
    for p, q in np.argwhere(around):                   # p's box within q's
        vertex = s.triangles[s.triangle_piece == p][:1, 0]
        if inside(s, q, s.x[vertex])[0]:
            inner, outer = s.names[s.piece_body[p]], s.names[s.piece_body[q]]
            what = (f"a piece of body \"{inner}\" starts inside another" if inner == outer
                    else f"body \"{inner}\" starts inside body \"{outer}\"")
            move, direction = separation(s, p, q)
            raise FemError(f"{where}: {what} (it would have to move {mm(move)} along {direction} to come "
                           f"out); contact cannot separate a body that starts inside another: move it out")


def separation(s, p, q):
    """(m, 'x' | 'y' | 'z' | 'the line between their centres'): the least move of piece p, along
    an axis or the line between the pieces' centres, that clears piece q (where their extents
    along it no longer overlap): 350 mm along y for 1 m cubes 0.65 m apart, one above the other."""
    P, Q = s.x[s.piece == p], s.x[s.piece == q]
    line = Q.mean(axis=0) - P.mean(axis=0)
    directions = {"x": np.eye(3)[0], "y": np.eye(3)[1], "z": np.eye(3)[2],
                  "the line between their centres": line / max(np.linalg.norm(line), 1e-300)}
    moves = {name: min((Q @ d).max() - (P @ d).min(), (P @ d).max() - (Q @ d).min())
             for name, d in directions.items()}
    name = min(moves, key=moves.get)
    return float(moves[name]), name


def check_gaps(where, s, d_hat):
    """Pieces closer than d_hat: refused with the smallest gap. Only the triangles, edges and
    vertices within d_hat of another piece's box are paired (none where bodies are far apart)."""
    gaps = []
    centre, radius = triangle_spheres(s)
    t = np.flatnonzero(exposed(s, s.triangle_piece, centre, radius + d_hat))
    v = np.unique(s.triangles)
    v = v[exposed(s, s.piece[v], s.x[v], np.full(len(v), d_hat))]
    i, j = near(centre[t], radius[t] + d_hat, s.x[v], np.zeros(len(v)))
    t, v = t[i], v[j]
    keep = s.piece[v] != s.triangle_piece[t]
    v, t = v[keep], t[keep]
    gaps.append((point_triangle_distance(s.x[v], *s.x[s.triangles[t]].transpose(1, 0, 2)),
                 s.piece[v], s.triangle_piece[t]))
    middle, half = edge_spheres(s)
    e = np.flatnonzero(exposed(s, s.piece[s.edges[:, 0]], middle, half + d_hat))
    i, j = near(middle[e], half[e] + d_hat, middle[e], half[e])
    e, f = e[i], e[j]
    a, b = s.piece[s.edges[e, 0]], s.piece[s.edges[f, 0]]
    keep = (e < f) & (a != b)
    e, f, a, b = e[keep], f[keep], a[keep], b[keep]
    p0, p1 = s.x[s.edges[e, 0]], s.x[s.edges[e, 1]]
    gaps.append((segment_distance(p0, p1, s.x[s.edges[f, 0]], s.x[s.edges[f, 1]]), a, b))
    distance, a, b = (np.concatenate(g) for g in zip(*gaps))
    close = distance < d_hat
    if not close.any():
        return
    pairs = {tuple(sorted(pair)) for pair in zip(a[close], b[close])}
    k = np.flatnonzero(close)[np.argmin(distance[close])]
    others = f" (and {len(pairs) - 1} more pairs)" if len(pairs) > 1 else ""
    raise FemError(f"{where}: {s.between(*sorted((a[k], b[k])))} start {mm(distance[k])} apart{others}, closer "
                   f"than the contact distance ({mm(d_hat)}), which would throw them apart in the first step: "
                   f"place them at least {mm(d_hat)} apart, or use a smaller contact distance")


# ---------------------------------------------------------------- candidates

def near(centres, radii, other_centres, other_radii):
    """(i, j): every two spheres, one of each list, that meet: |centres[i] - other_centres[j]| <=
    radii[i] + other_radii[j] (k-d trees list the pairs within the largest sum in C)."""
    if not len(centres) or not len(other_centres):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    reach = radii.max() + other_radii.max()
    pairs = cKDTree(centres).sparse_distance_matrix(cKDTree(other_centres), reach, output_type="ndarray")
    i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    keep = pairs["v"] <= radii[i] + other_radii[j]
    return i[keep], j[keep]


def exposed(s, pieces, centres, radii):
    """(k,) bool: the spheres (centres (k, 3), radii (k,)) of elements of the given pieces (k,) that
    reach into the box of another piece."""
    out = np.zeros(len(centres), bool)
    for q in np.flatnonzero(np.isfinite(s.lo[:, 0])):
        reach = ((centres + radii[:, None] >= s.lo[q]) & (centres - radii[:, None] <= s.hi[q])).all(axis=1)
        out |= reach & (pieces != q)
    return out


def triangle_spheres(s):
    """(centres (t, 3), radii (t,)): a sphere around each surface triangle."""
    corners = s.x[s.triangles]
    centre = corners.mean(axis=1)
    return centre, np.linalg.norm(corners - centre[:, None], axis=2).max(axis=1)


def edge_spheres(s):
    """(midpoints (e, 3), half lengths (e,)) of the surface edges."""
    p0, p1 = s.x[s.edges[:, 0]], s.x[s.edges[:, 1]]
    return (p0 + p1) / 2, np.linalg.norm(p1 - p0, axis=1) / 2


def crossings(s):
    """(edge ids, triangle ids): the surface edges through a surface triangle (its sides and corners
    included) that shares no vertex with them, their ends on either side of its plane (edges in
    the plane, as where faces touch, do not cross)."""
    middle, half = edge_spheres(s)
    centre, radius = triangle_spheres(s)
    t, e = near(centre, radius, middle, half)
    a = s.x[s.triangles[:, 0]]
    normal = np.cross(s.x[s.triangles[:, 1]] - a, s.x[s.triangles[:, 2]] - a)
    p, q = s.x[s.edges[e, 0]], s.x[s.edges[e, 1]]
    normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-300)[:, None]
    height_p, height_q = np.einsum("ij,ij->i", normal[t], p - a[t]), np.einsum("ij,ij->i", normal[t], q - a[t])
    rounding = ROUNDING * np.abs(s.x).max()
    sides = (height_p * height_q < 0) & (np.minimum(np.abs(height_p), np.abs(height_q)) > rounding)
    t, e, p, q = t[sides], e[sides], p[sides], q[sides]              # the ends on either side of its plane
    a, b, c = s.x[s.triangles[t]].transpose(1, 0, 2)
    length = np.linalg.norm(q - p, axis=1)
    around = np.stack([orient(p, q, u, v) / (length * np.linalg.norm(v - u, axis=1))
                       for u, v in ((a, b), (b, c), (c, a))])          # m: which side of each side it passes
    through = (around >= -rounding).all(axis=0) | (around <= rounding).all(axis=0)
    alone = ~(s.triangles[t][:, :, None] == s.edges[e][:, None, :]).any(axis=(1, 2))
    hit = through & alone
    return e[hit], t[hit]


def orient(a, b, c, d):
    """Six times the signed volume of each tet (a, b, c, d), rows of (k, 3) each."""
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)


# ---------------------------------------------------------------- inside

def inside(s, piece, points):
    """(k,) bool: each point (k, 3) inside the piece's closed surface: a ray along RAY from it
    crosses the surface an odd number of times (Moeller and Trumbore's ray-triangle test)."""
    a, b, c = s.x[s.triangles[s.triangle_piece == piece]].transpose(1, 0, 2)
    e1, e2 = b - a, c - a
    h = np.cross(RAY, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-30
    a, e1, e2, h, det = a[ok], e1[ok], e2[ok], h[ok], det[ok]
    hits = np.zeros(len(points), np.int64)
    step = max(1, CHUNK // max(len(a), 1))
    for start in range(0, len(points), step):
        w = points[start:start + step, None, :] - a[None]                     # (k, t, 3)
        u = np.einsum("ktj,tj->kt", w, h) / det
        q = np.cross(w, e1[None])
        v = (q @ RAY) / det
        t = np.einsum("ktj,tj->kt", q, e2) / det
        hits[start:start + step] = ((u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)).sum(axis=1)
    return hits % 2 == 1


# ---------------------------------------------------------------- exact distances

def point_segment_distance(p, a, b):
    """(k,) distance from points p to segments (a, b), rows of (k, 3) each."""
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def point_triangle_distance(p, a, b, c):
    """(k,) distance from points p to triangles (a, b, c): to the plane where p's projection falls
    inside the triangle, else to the nearest side."""
    n = np.cross(b - a, c - a)
    area2 = np.maximum(np.einsum("ij,ij->i", n, n), 1e-300)
    height = np.einsum("ij,ij->i", p - a, n)
    foot = p - (height / area2)[:, None] * n
    within = np.ones(len(p), bool)
    for u, v in ((a, b), (b, c), (c, a)):
        within &= np.einsum("ij,ij->i", np.cross(v - u, foot - u), n) >= 0
    sides = np.minimum.reduce([point_segment_distance(p, a, b), point_segment_distance(p, b, c),
                               point_segment_distance(p, c, a)])
    return np.where(within, np.abs(height) / np.sqrt(area2), sides)


def segment_distance(p0, p1, q0, q1):
    """(k,) distance between segments (p0, p1) and (q0, q1): at the lines' closest points where
    both fall inside the segments, else from an end to the other segment."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, b = (np.einsum("ij,ij->i", u, w) for u, w in ((d1, d1), (d2, d2), (d1, d2)))
    c, f = np.einsum("ij,ij->i", d1, r), np.einsum("ij,ij->i", d2, r)
    denominator = a * e - b * b
    parallel = denominator <= 1e-12 * np.maximum(a * e, 1e-300)
    safe = np.where(parallel, 1.0, denominator)
    s, t = (b * f - c * e) / safe, (a * f - b * c) / safe
    interior = ~parallel & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    lines = np.linalg.norm(p0 + s[:, None] * d1 - q0 - t[:, None] * d2, axis=1)
    ends = np.minimum.reduce([point_segment_distance(p0, q0, q1), point_segment_distance(p1, q0, q1),
                              point_segment_distance(q0, p0, p1), point_segment_distance(q1, p0, p1)])
    return np.where(interior, np.minimum(lines, ends), ends)
