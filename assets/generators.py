"""Procedural tet meshes: a box, a "dome" on legs and a holed "statue".

The dome and the statue stand in for the coursework's epcot and fertility
meshes, which the project may not ship. Both are built by `assets.lattice`
from signed distance functions (metres, negative inside), with y up. All
generators are deterministic and take well under a second at their defaults.
"""

import math

import numpy as np

from assets.lattice import implicit_mesh, lattice_mesh
from fem.errors import FemError
from fem.limits import MAX_DOME_LEGS, amount, check_size
from fem.mesh import check_tet_count


def box(size=(1.0, 1.0, 1.0), cells=(4, 4, 4), split=5):
    """A box of `size` metres centred at the origin, `cells` lattice cells per
    axis, each split into `split` tets: 5 (alternating mirror images so faces
    conform) or 6 (Kuhn, around each cell's main diagonal).
    """
    size = _vector("size", size, float)
    cells = _vector("cells", cells, int)
    _require(split in (5, 6), f"split must be 5 or 6, got {split!r}")
    _require(all(s > 0 for s in size), f"size must be positive, got {size}")
    _require(all(c >= 1 for c in cells), f"cells must be >= 1, got {cells}")
    source = f"box(size={size}, cells={cells}, split={split})"
    count = int(np.prod(cells, dtype=object)) * split          # before the lattice is allocated
    check_tet_count(count, source, f"{amount(count)} tets")
    spacing = np.array(size) / np.array(cells)
    return lattice_mesh(np.ones(cells, dtype=bool), -0.5 * np.array(size), spacing, split,
                        source)


def dome(radius=1.0, subdivisions=2, legs=3, leg_length=0.8, leg_radius=0.15, resolution=12):
    """A geodesic sphere standing on legs (a stand-in for the epcot mesh).

    radius: of the sphere, metres, centred at the origin. subdivisions: of
    the icosahedron whose flat facets the surface is snapped to (2 gives 320
    facets). legs: vertical cylinders of `leg_radius` metres reaching
    `leg_length` metres below the sphere, evenly spaced around the y axis at
    half the radius from it. resolution: lattice cells across the sphere's
    diameter (the tet count grows as its cube; 12 gives about 5k tets).
    Each leg axis is moved to the nearest lattice line, so that a leg is at
    least two cells thick whatever the resolution.
    """
    _require(radius > 0, f"radius must be > 0, got {radius!r}")
    _require(isinstance(subdivisions, int) and 0 <= subdivisions <= 5,
             f"subdivisions must be an integer 0..5, got {subdivisions!r}")
    _require(isinstance(legs, int) and legs >= 0, f"legs must be an integer >= 0, got {legs!r}")
    check_size(legs, MAX_DOME_LEGS, "dome", f"{amount(legs)} legs")
    _require(leg_length > 0, f"leg_length must be > 0, got {leg_length!r}")
    _require(0 < leg_radius < radius, f"leg_radius must be in (0, radius), got {leg_radius!r}")
    _require(isinstance(resolution, int) and resolution >= 4,
             f"resolution must be an integer >= 4, got {resolution!r}")
    spacing = 2.0 * radius / resolution
    normals, offsets = _geodesic_planes(radius, subdivisions)

    foot_distance = 0.5 * radius
    top = 0.0                                  # legs start at the centre, hidden inside
    bottom = -np.sqrt(radius**2 - foot_distance**2) - leg_length
    angles = np.pi / 2 + 2 * np.pi * np.arange(legs) / max(legs, 1)
    axes = foot_distance * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    axes = np.round(axes / spacing) * spacing  # on lattice lines (lattice is centred)

    def sdf(p):
        # einsum: much faster than BLAS matmul for these thin shapes.
        distance = (np.einsum("ij,kj->ik", p, normals) - offsets).max(axis=1)
        for ax, az in axes:
            distance = np.minimum(distance, _vertical_cylinder(p, ax, az, leg_radius,
                                                               bottom, top))
        return distance

    lower = np.array([-radius, bottom if legs else -radius, -radius])
    upper = np.array([radius, radius, radius])
    lower, upper = _centre_lattice(lower, upper, spacing)
    source = (f"dome(radius={radius}, subdivisions={subdivisions}, legs={legs}, "
              f"leg_length={leg_length}, leg_radius={leg_radius}, resolution={resolution})")
    return implicit_mesh(sdf, lower, upper, spacing, source)


def statue(resolution=22):
    """A 1.5 m statue with genus 3 (a stand-in for the fertility mesh).

    A torso, neck and head on two legs that stand on a plinth, with both
    hands on the hips: the two arm loops and the gap between the legs are
    three holes through the body. resolution: lattice cells across the height
    (the tet count grows as its cube; 22 gives about 2.5k tets).
    """
    _require(isinstance(resolution, int) and resolution >= 16,
             f"resolution must be an integer >= 16 (thinner limbs break up), "
             f"got {resolution!r}")
    height = 1.5
    spacing = height / resolution

    def sdf(p):
        parts = [
            _box(p, [0.0, 0.06, 0.0], [0.32, 0.06, 0.2]),                        # plinth
            _capsule(p, [-0.2, 0.08, 0.0], [-0.12, 0.62, 0.0], 0.085),           # legs
            _capsule(p, [0.2, 0.08, 0.0], [0.12, 0.62, 0.0], 0.085),
            _ellipsoid(p, [0.0, 0.86, 0.0], [0.25, 0.36, 0.15]),                 # torso
            _capsule(p, [0.0, 1.12, 0.0], [0.0, 1.3, 0.0], 0.08),                # neck
            _ellipsoid(p, [0.0, 1.36, 0.0], [0.12, 0.14, 0.13]),                 # head
            _torus_z(p, [-0.36, 0.9, 0.0], 0.18, 0.075),                          # arms
            _torus_z(p, [0.36, 0.9, 0.0], 0.18, 0.075),
        ]
        return np.min(parts, axis=0)

    lower, upper = _centre_lattice(np.array([-0.62, 0.0, -0.2]), np.array([0.62, 1.5, 0.2]),
                                   spacing)
    return implicit_mesh(sdf, lower, upper, spacing, f"statue(resolution={resolution})")


def _require(condition, message):
    if not condition:
        raise FemError(message)


def _vector(name, value, kind):
    """Three numbers of type `kind` (int accepts only integers)."""
    try:
        values = tuple(value)
    except TypeError:
        raise FemError(f"{name} must be three numbers, got {value!r}") from None
    ok = len(values) == 3 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool)
        and (kind is float or float(v).is_integer()) and _finite(v) for v in values)
    _require(ok, f"{name} must be three {'integers' if kind is int else 'numbers'}, "
                 f"got {value!r}")
    return tuple(kind(v) for v in values)


def _finite(number):
    """An int is finite however large (1e20 cells reaches the size check, which says why not)."""
    return isinstance(number, int) or math.isfinite(number)


def _centre_lattice(lower, upper, spacing):
    """Grow [lower, upper] to whole cells, symmetric about x = z = 0 so that
    lattice lines pass through the y axis (the lattice origin stays on it)."""
    half = np.ceil(np.maximum(-lower, upper) / spacing) * spacing
    return np.array([-half[0], lower[1], -half[2]]), np.array([half[0], upper[1], half[2]])


def _geodesic_planes(radius, subdivisions):
    """Outward unit normals (f, 3) and offsets (f,) of the facets of an
    icosphere of circumradius `radius`: the solid is {p : normals @ p <= offsets}.

    The icosahedron's triangles are split into four, `subdivisions` times,
    with the new vertices pushed out onto the sphere.
    """
    t = (1.0 + np.sqrt(5.0)) / 2.0
    vertices = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    faces = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
             [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
             [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
             [8, 6, 7], [9, 8, 1]]
    vertices = [np.array(v) / np.linalg.norm(v) for v in vertices]
    midpoint_of = {}

    def midpoint(i, j):
        key = (min(i, j), max(i, j))
        if key not in midpoint_of:
            m = vertices[i] + vertices[j]
            vertices.append(m / np.linalg.norm(m))
            midpoint_of[key] = len(vertices) - 1
        return midpoint_of[key]

    for _ in range(subdivisions):
        split = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            split += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = split
    corners = radius * np.array(vertices)[np.array(faces)]            # (f, 3, 3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return normals, np.einsum("ij,ij->i", normals, corners[:, 0])


def _box(p, centre, half):
    q = np.abs(p - centre) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def _capsule(p, a, b, r):
    a, b = np.asarray(a), np.asarray(b)
    t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * (b - a), axis=1) - r


def _ellipsoid(p, centre, radii):
    """A close bound on the distance (exact on the axes), good enough for meshing."""
    q = (p - centre) / radii
    k0 = np.linalg.norm(q, axis=1)
    k1 = np.linalg.norm(q / radii, axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _torus_z(p, centre, major, minor):
    """Torus in the x-y plane (around the z axis)."""
    q = p - centre
    ring = np.hypot(q[:, 0], q[:, 1]) - major
    return np.hypot(ring, q[:, 2]) - minor


def _vertical_cylinder(p, x, z, r, bottom, top):
    radial = np.hypot(p[:, 0] - x, p[:, 2] - z) - r
    axial = np.maximum(bottom - p[:, 1], p[:, 1] - top)
    outside = np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0))
    return outside + np.minimum(np.maximum(radial, axial), 0.0)
