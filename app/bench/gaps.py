"""How close the bodies of a pile came, measured from their vertex positions alone, the same way for
this project's steps and for the peer's (app/bench/contact.py):

    gap         the smallest distance between the surfaces of two different bodies, m: the least of
                every vertex-to-triangle and edge-to-edge distance between them (two triangle meshes
                that do not cross are nearest at one of those)
    crossed     whether a vertex of one body lies inside another body (then the gap says nothing)
    sunk        how deep the deepest vertex lies under the ground, m (0 when none does)

Pairs of bodies whose bounding boxes lie farther apart than REACH are not looked at.
"""

import itertools

import numpy as np

REACH = 0.05   # m: farther apart than this, a pair's gap does not matter (contact distances are about 0.01)


def surface(tets):
    """(triangles (k, 3), edges (e, 2)): the faces of `tets` that belong to one tet only, and their edges."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    _, first, count = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    triangles = faces[first[count == 1]]
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    return triangles, np.unique(edges, axis=0)


def point_triangle(p, a, b, c):
    """(k,) distances from points p (k, 3) to triangles abc (k, 3 each): the closest point's region by
    its barycentric coordinates (Ericson, Real-Time Collision Detection, 5.1.5), vectorised."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp, cp = p - b, p - c
    d3, d4, d5, d6 = dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    v, w = vb / safe(va + vb + vc), vc / safe(va + vb + vc)      # inside the face, unless
    t_bc = (d4 - d3) / safe(d4 - d3 + d5 - d6)
    cases = [((d1 <= 0) & (d2 <= 0), 0, 0),                                  # corner a
             ((d3 >= 0) & (d4 <= d3), 1, 0),                                 # corner b
             ((vc <= 0) & (d1 >= 0) & (d3 <= 0), d1 / safe(d1 - d3), 0),      # edge ab
             ((d6 >= 0) & (d5 <= d6), 0, 1),                                 # corner c
             ((vb <= 0) & (d2 >= 0) & (d6 <= 0), 0, d2 / safe(d2 - d6)),      # edge ac
             ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 1 - t_bc, t_bc)]   # edge bc
    for where, case_v, case_w in reversed(cases):              # the first case that holds wins
        v, w = np.where(where, case_v, v), np.where(where, case_w, w)
    closest = a + v[:, None] * ab + w[:, None] * ac
    return np.linalg.norm(p - closest, axis=1)


def segment_segment(p, q, r, s):
    """(k,) distances between segments pq and rs (k, 3 each) (Ericson, 5.1.9), vectorised; parallel
    segments are measured from r's end."""
    d1, d2, w = q - p, s - r, p - r
    a, e, b, c, f = dot(d1, d1), dot(d2, d2), dot(d1, d2), dot(d1, w), dot(d2, w)
    denominator = a * e - b * b
    t1 = np.where(denominator > 1e-12 * a * e, np.clip((b * f - c * e) / safe(denominator), 0, 1), 0.0)
    t2 = (b * t1 + f) / e
    t1 = np.where(t2 < 0, np.clip(-c / a, 0, 1), np.where(t2 > 1, np.clip((b - c) / a, 0, 1), t1))
    t2 = np.clip(t2, 0, 1)
    return np.linalg.norm(p + t1[:, None] * d1 - r - t2[:, None] * d2, axis=1)


def inside(p, tets_x):
    """(k,) whether points p (k, 3) lie strictly inside tets with corners tets_x (k, 4, 3)."""
    edges = np.transpose(tets_x[:, 1:] - tets_x[:, :1], (0, 2, 1))
    coords = np.linalg.solve(edges, (p - tets_x[:, 0])[..., None])[..., 0]
    return (coords > 0).all(axis=1) & (coords.sum(axis=1) < 1)


def dot(u, v):
    return np.einsum("ij,ij->i", u, v)


def safe(x):
    """x, with 1 where it is 0: a denominator whose zero case another branch takes."""
    return np.where(x == 0, 1.0, x)


def every(first, second):
    """Every row of `first` beside every row of `second`: (len(first) len(second) rows of each)."""
    return np.repeat(first, len(second), axis=0), np.tile(second, (len(first),) + (1,) * (second.ndim - 1))


def by_body(items, body):
    """[the rows of `items` (vertex ids, or rows of them) on body b, for each body b]: by their first vertex."""
    first = items if items.ndim == 1 else items[:, 0]
    return [items[body[first] == b] for b in range(body.max() + 1)]


class Surfaces:
    """The surfaces of a pile's bodies, to measure how close they come (gap, crossed, sunk)."""

    def __init__(self, tets, body):
        """tets (m, 4) and body (n,), each vertex's body: the pile's mesh, vertex ids global."""
        triangles, edges = surface(tets)
        self.vertices_of = by_body(np.arange(len(body)), body)
        self.triangles_of = by_body(triangles, body)
        self.edges_of = by_body(edges, body)
        self.tets_of = by_body(tets, body)

    def near_pairs(self, x):
        """Ordered pairs (a, b), a != b, of bodies whose bounding boxes come within REACH."""
        low = np.array([x[ids].min(axis=0) for ids in self.vertices_of])
        high = np.array([x[ids].max(axis=0) for ids in self.vertices_of])
        return [(a, b) for a, b in itertools.permutations(range(len(low)), 2)
                if (low[a] <= high[b] + REACH).all() and (low[b] <= high[a] + REACH).all()]

    def measure(self, x, ground):
        """{"gap": m (None when no pair comes within REACH), "crossed": bool, "sunk": m} of positions x (n, 3)."""
        sunk = max(0.0, float(ground - x[:, 1].min()))
        pairs = self.near_pairs(x)
        if not pairs:
            return {"gap": None, "crossed": False, "sunk": sunk}
        point, triangle = map(np.concatenate, zip(*[every(self.vertices_of[a], self.triangles_of[b])
                                                    for a, b in pairs]))
        gap = point_triangle(x[point], *(x[triangle[:, k]] for k in range(3))).min()
        one, two = map(np.concatenate, zip(*[every(self.edges_of[a], self.edges_of[b]) for a, b in pairs if a < b]))
        gap = min(gap, segment_segment(x[one[:, 0]], x[one[:, 1]], x[two[:, 0]], x[two[:, 1]]).min())
        return {"gap": float(gap), "crossed": any(self.crossed(x, a, b) for a, b in pairs), "sunk": sunk}

    def crossed(self, x, a, b):
        """Whether a vertex of body a lies inside body b."""
        vertex, tet = every(self.vertices_of[a], self.tets_of[b])
        return bool(inside(x[vertex], x[tet]).any())
