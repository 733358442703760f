"""Tet meshes from a cubic lattice: boxes, voxelised implicit shapes, snapping.

A shape is given by a signed distance function `sdf(points) -> (k,)`, negative
inside, in metres. `implicit_mesh` keeps the lattice cells whose centre is
inside, repairs the cell set so its boundary is a closed 2-manifold, splits each
cell into tets, and finally moves boundary vertices onto the surface as far as
the tets' quality allows. Each step keeps the mesh conforming, so the result is
valid for FEM whatever the shape.
"""

import math

import numpy as np

from fem.limits import amount
from fem.mesh import (boundary_faces, check_tet_count, dihedral_angles, prepare_mesh,
                      signed_volumes)

# Cell corners are numbered by their offset bits: corner c sits at
# (c & 1, (c >> 1) & 1, (c >> 2) & 1) cell widths from the cell's lowest corner.
CORNER_OFFSETS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])

# Five tets: four corner tets around the regular tet (1, 2, 4, 7). Cells of
# odd parity use the mirror image (corner c -> c ^ 1), so that neighbouring
# cells cut their shared face along the same diagonal.
FIVE_TETS = np.array([[0, 1, 2, 4], [3, 1, 2, 7], [5, 1, 4, 7], [6, 2, 4, 7], [1, 2, 4, 7]])

# Six tets around the main diagonal 0-7 (Kuhn / Freudenthal): one per path
# 0 -> 7 along the axes. Every cell cuts its faces the same way, so the
# split conforms without alternating.
SIX_TETS = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7],
                     [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])

# Pairs of opposite cells in a 2x2x2 block, as offset triples.
OPPOSITE_CELLS = [((0, 0, 0), (1, 1, 1)), ((1, 0, 0), (0, 1, 1)),
                  ((0, 1, 0), (1, 0, 1)), ((0, 0, 1), (1, 1, 0))]


def lattice_mesh(filled, origin, spacing, split, source):
    """Split every filled cell of a lattice into tets.

    filled: (nx, ny, nz) bool, one entry per cell. origin: (3,) position of the
    lowest corner of cell (0, 0, 0), metres. spacing: (3,) cell size, metres.
    split: 5 or 6 tets per cell. Returns a checked `TetMesh` with only the
    lattice nodes that some tet uses.
    """
    filled = np.asarray(filled, dtype=bool)
    check_tet_count(int(filled.sum()) * split, source)
    cells = np.argwhere(filled)                                   # (c, 3) cell indices
    nodes_shape = np.array(filled.shape) + 1
    corners = cells[:, None, :] + CORNER_OFFSETS[None]           # (c, 8, 3) node indices
    node_ids = np.ravel_multi_index(corners.reshape(-1, 3).T, nodes_shape).reshape(-1, 8)
    if split == 5:
        odd = cells.sum(axis=1) % 2 == 1
        local = np.where(odd[:, None, None], FIVE_TETS ^ 1, FIVE_TETS)
        tets = np.take_along_axis(node_ids[:, None, :], local, axis=2).reshape(-1, 4)
    else:
        tets = node_ids[:, SIX_TETS].reshape(-1, 4)
    used, tets = np.unique(tets, return_inverse=True)
    positions = np.stack(np.unravel_index(used, nodes_shape), axis=1)
    vertices = np.asarray(origin) + positions * np.asarray(spacing)
    return prepare_mesh(vertices, tets.reshape(-1, 4), source)


def implicit_mesh(sdf, lower, upper, spacing, source, min_dihedral_deg=12.0):
    """Tet mesh of the shape {sdf < 0} inside the box [lower, upper].

    sdf: (k, 3) points -> (k,) signed distance, metres, negative inside.
    spacing: the lattice cell size, metres. Cells are split into 5 tets.
    Boundary vertices are then moved onto the surface unless a move would
    make some tet's smallest dihedral angle drop below `min_dihedral_deg`.
    """
    lower = np.asarray(lower, dtype=np.float64) - spacing     # one empty cell all round
    # Python integers: a resolution of 1e20 would wrap numpy's 64-bit product round.
    counts = [math.ceil(n) for n in (np.asarray(upper) + spacing - lower) / spacing]
    lattice = math.prod(counts)
    # Before the lattice is allocated (lattice_mesh counts the cells the shape fills, 5 tets each).
    check_tet_count(lattice, source, f"a lattice of {amount(lattice)} cells (at least one tet each)")
    centres = lower + (np.argwhere(np.ones(counts, dtype=bool)) + 0.5) * spacing
    filled = manifold_cells(sdf(centres).reshape(counts) < 0)
    mesh = lattice_mesh(filled, lower, [spacing] * 3, 5, source)
    mesh.vertices = snap_to_surface(mesh.vertices, mesh.tets, sdf, spacing,
                                    np.radians(min_dihedral_deg))
    return mesh


def manifold_cells(filled):
    """A cell set near `filled` whose boundary is one closed 2-manifold.

    The boundary of a union of cubes is a manifold exactly when no 2x2 ring of
    cells around an edge, and no 2x2x2 block, is filled in a checkerboard-like
    way (the "critical configurations" of 3-D digital topology). Those are
    filled in; then only the largest face-connected piece is kept and its
    inner cavities are filled, so the surface is a single closed sheet.
    """
    from scipy import ndimage         # here, not at the top: a run that builds no lattice never imports it

    filled = filled.copy()
    while True:
        before = filled.copy()
        _fill_critical_configurations(filled)
        labels, count = ndimage.label(filled)
        if count > 1:
            sizes = np.bincount(labels.ravel())[1:]
            filled = labels == 1 + np.argmax(sizes)
        filled = ndimage.binary_fill_holes(filled)
        if np.array_equal(filled, before):
            return filled


def _fill_critical_configurations(filled):
    """Fill, in place, every critical 2x2 ring and 2x2x2 block of `filled`."""
    nx, ny, nz = filled.shape

    def block(dx, dy, dz):
        """View of the cell at offset (dx, dy, dz) in every 2x2x2 block."""
        return filled[dx:nx - 1 + dx, dy:ny - 1 + dy, dz:nz - 1 + dz]

    while True:
        changed = False
        # Rings around edges: two diagonal cells filled, the other two empty.
        for axis in range(3):
            for layer in (0, 1):
                ring = []
                for a in (0, 1):
                    for b in (0, 1):
                        offset = [a, b]
                        offset.insert(axis, layer)
                        ring.append(block(*offset))
                c00, c01, c10, c11 = ring
                critical = (c00 & c11 & ~c01 & ~c10) | (c01 & c10 & ~c00 & ~c11)
                if critical.any():
                    changed = True
                    for cell in ring:
                        cell |= critical
        # Blocks: two opposite cells alone, or two opposite holes alone.
        cells = {offset: block(*offset) for offset in map(tuple, CORNER_OFFSETS)}
        count = sum(cell.astype(np.int8) for cell in cells.values())
        critical = np.zeros_like(count, dtype=bool)
        for first, second in OPPOSITE_CELLS:
            pair = cells[first] & cells[second]
            none = ~cells[first] & ~cells[second]
            critical |= (pair & (count == 2)) | (none & (count == 6))
        if critical.any():
            changed = True
            for cell in cells.values():
                cell |= critical
        if not changed:
            return


def project_to_surface(sdf, points, spacing, iterations=3):
    """Newton steps p <- p - f(p) grad f / |grad f|^2 towards {sdf = 0}.

    The gradient is taken by finite differences of step 1e-4 * spacing, so
    any union or intersection of primitives works. Returns (k, 3) metres.
    """
    step = 1e-4 * spacing
    for _ in range(iterations):
        value = sdf(points)
        gradient = np.stack([(sdf(points + step * e) - value) / step for e in np.eye(3)],
                            axis=1)
        length_squared = np.maximum(np.einsum("ij,ij->i", gradient, gradient), 1e-12)
        points = points - (value / length_squared)[:, None] * gradient
    return points


def snap_to_surface(vertices, tets, sdf, spacing, min_dihedral):
    """Move boundary vertices onto {sdf = 0} while every tet stays good.

    A tet is good when its volume is positive and its smallest dihedral angle
    is at least `min_dihedral` radians. Moves are tried whole, then by halves
    and quarters; a move is undone for every vertex of a tet it made bad, until
    no bad tet is left, so the result is never worse than the input's bound.
    Returns the new (n, 3) vertices.
    """
    vertices = vertices.copy()
    boundary = np.unique(boundary_faces(tets))
    for fraction in (1.0, 1.0, 0.5, 0.5, 0.25, 0.25):
        target = project_to_surface(sdf, vertices[boundary], spacing)
        trial = vertices.copy()
        trial[boundary] += fraction * (target - vertices[boundary])
        while True:
            bad = ((signed_volumes(trial, tets) <= 0)
                   | ~(dihedral_angles(trial, tets).min(axis=1) >= min_dihedral))
            moved = np.any(trial != vertices, axis=1)
            undo = np.unique(tets[bad])
            undo = undo[moved[undo]]
            if len(undo) == 0:
                break
            trial[undo] = vertices[undo]
        vertices = trial
    return vertices
