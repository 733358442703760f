"""Picking: which surface point a mouse click hits, and which vertices it pushes.

Pure numpy, so it can be tested without a window:

    hit = pick(origin, direction, positions, model.surface)   # None: empty space
    ids, dv = push(positions, body_vertices, hit.point, radius, delta_v)
    sim.apply_impulse(ids, dv)
"""

from dataclasses import dataclass

import numpy as np

EPSILON = 1e-12


@dataclass
class Hit:
    """Where a ray first meets the surface.

    triangle: row of the triangle list that was hit; point (3,) metres;
    distance: metres from the ray's origin; vertex: the hit triangle's corner
    nearest to the point (a global vertex id).
    """

    triangle: int
    point: np.ndarray
    distance: float
    vertex: int


def ray_triangle_distances(origin, direction, vertices, triangles) -> np.ndarray:
    """Distance along the ray to every triangle, inf where the ray misses it (shape (k,)).

    Moller-Trumbore for all triangles at once. origin (3,), unit direction (3,),
    vertices (n, 3), triangles (k, 3) int. Both sides of a triangle count as hits,
    and only hits in front of the origin (distance > 0).
    """
    origin = np.asarray(origin, np.float64)
    direction = np.asarray(direction, np.float64)
    a, b, c = (np.asarray(vertices, np.float64)[triangles[:, i]] for i in range(3))
    edge1, edge2 = b - a, c - a
    p = np.cross(direction, edge2)
    det = np.einsum("ij,ij->i", edge1, p)
    usable = np.abs(det) > EPSILON            # the ray is not parallel to the triangle
    inv_det = np.where(usable, 1.0 / np.where(usable, det, 1.0), 0.0)
    s = origin - a
    u = np.einsum("ij,ij->i", s, p) * inv_det
    q = np.cross(s, edge1)
    v = (q @ direction) * inv_det
    t = np.einsum("ij,ij->i", edge2, q) * inv_det
    inside = usable & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > EPSILON)
    return np.where(inside, t, np.inf)


def pick(origin, direction, vertices, triangles) -> Hit | None:
    """The nearest triangle the ray hits, or None when it hits nothing."""
    distances = ray_triangle_distances(origin, direction, vertices, triangles)
    nearest = int(np.argmin(distances)) if len(distances) else 0
    if not len(distances) or not np.isfinite(distances[nearest]):
        return None
    point = np.asarray(origin, np.float64) + distances[nearest] * np.asarray(direction, np.float64)
    corners = np.asarray(triangles[nearest])
    closest = corners[np.argmin(np.linalg.norm(np.asarray(vertices)[corners] - point, axis=1))]
    return Hit(nearest, point, float(distances[nearest]), int(closest))


def falloff(distances, radius: float) -> np.ndarray:
    """Weights in [0, 1] for points at `distances` from the hit point (any shape).

    (1 - (d / radius)^2)^2 inside the radius, 0 outside: 1 at the hit point,
    and smooth (zero slope) both at the centre and at the radius, so the pushed
    patch has no crease or step at its edge.
    """
    x = np.clip(np.asarray(distances, np.float64) / radius, 0.0, 1.0)
    return (1.0 - x * x) ** 2


def push(positions, candidates, point, radius: float, delta_v):
    """The vertices a click pushes and the velocity change of each.

    positions (n, 3) metres; candidates: global ids of the vertices that may be
    pushed (the hit body's); point (3,) the hit point; radius metres; delta_v (3,)
    m/s at the hit point. Returns (ids (m,), dv (m, 3)), the vertices within
    the radius and delta_v scaled by their falloff weight.
    """
    candidates = np.asarray(candidates)
    distances = np.linalg.norm(np.asarray(positions)[candidates] - np.asarray(point), axis=1)
    near = distances < radius
    weights = falloff(distances[near], radius)
    return candidates[near], weights[:, None] * np.asarray(delta_v, np.float64)[None, :]


def mirrored(ids, body_starts, body, twin):
    """Global ids of the same local vertices in body `twin` (compare mode's other copy).

    body_starts: first global vertex id of each body; ids lie in body `body`.
    """
    return np.asarray(ids) - body_starts[body] + body_starts[twin]
