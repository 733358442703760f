"""The builder: a Scene (a description) becomes the arrays of a Model and a start State.

    model.load(*model_arrays(scene))
    x, v = initial_state(scene, model)
"""

import numpy as np

from fem.mesh import boundary_faces
from fem.model import BodyInfo
from fem.scene import Material, select_vertices


def model_arrays(scene):
    """(bodies, X, T, mass, free): every body of the scene in one set of arrays, in the
    scene's body order, as `Model.load` takes them."""
    meshes = [b.mesh for b in scene.bodies]
    v_off = np.cumsum([0] + [len(m.vertices) for m in meshes])
    t_off = np.cumsum([0] + [len(m.tets) for m in meshes])
    X = np.concatenate([m.vertices for m in meshes])
    T = np.concatenate([m.tets + o for m, o in zip(meshes, v_off)]).astype(np.int32)
    Dm = np.stack([X[T[:, k]] - X[T[:, 3]] for k in range(3)], axis=2)
    W = np.abs(np.linalg.det(Dm)) / 6
    tet_body = np.repeat(np.arange(len(meshes)), np.diff(t_off))
    density = np.array([b.material.density for b in scene.bodies])[tet_body]
    mass = np.zeros(len(X))
    np.add.at(mass, T.ravel(), np.repeat(density * W / 4, 4))
    free = (mass > 0).astype(float)          # a vertex in no tet has no mass: keep it still
    bodies = []
    for i, b in enumerate(scene.bodies):
        free[b.pinned + v_off[i]] = 0.0
        vertices, tets = slice(v_off[i], v_off[i + 1]), slice(t_off[i], t_off[i + 1])
        bodies.append(BodyInfo(
            b.name, vertices, tets, rest_volume=float(W[tets].sum()),
            size=float(np.linalg.norm(np.ptp(b.mesh.vertices, axis=0))), mass=float(mass[vertices].sum()),
            surface=(boundary_faces(b.mesh.tets) + v_off[i]).astype(np.int32),
            material=Material(b.material.E, b.material.nu, b.material.density), method=b.method))
    return bodies, X, T, mass, free


def initial_state(scene, model):
    """(positions, velocities) at t = 0, (n, 3) each, with the scene's initial conditions applied."""
    return start_state(scene, model.bodies, model.rest_positions_np, model.mass_np, model.free_np)


def start_state(scene, bodies, X, mass, free):
    """initial_state from model_arrays' arrays, before any Model exists (the start's checks)."""
    x = X.copy()
    v = np.zeros_like(x)
    offsets = [b.vertices.start for b in bodies]
    for init in scene.initial:
        for body, ids in select_vertices(init.selection, scene.bodies, "initial condition"):
            g = ids + offsets[body]
            apply_initial(init, x, v, g, mass[g])
    return x, v * free[:, None]


def apply_initial(init, x, v, ids, mass):
    """Apply one initial condition to vertices `ids` of positions x and velocities v (in place).

    Velocities add up (so a spin and a push combine); shapes deform about the
    selection's centre of mass.
    """
    p = x[ids]
    centre = (mass[:, None] * p).sum(axis=0) / mass.sum()
    d = p - centre
    if init.kind == "velocity":
        v[ids] += init.value[0]
        return
    axis, amount = init.value
    along = d @ axis
    half_length = max(np.abs(along).max(), 1e-12)
    s = along / half_length                                 # -1 .. 1 along the axis
    if init.kind == "spin":
        v[ids] += amount * np.cross(axis, d)
    elif init.kind == "twist":
        v[ids] += amount * s[:, None] * np.cross(axis, d)
    elif init.kind == "stretch":
        x[ids] = p + (amount - 1) * along[:, None] * axis
    elif init.kind == "squash":
        # volume-preserving: factor along the axis, 1/sqrt(factor) across it
        across = d - along[:, None] * axis
        x[ids] = centre + amount * along[:, None] * axis + across / np.sqrt(amount)
    elif init.kind == "twist_shape":
        x[ids] = centre + rotate_about(d, axis, 0.5 * amount * s)
    elif init.kind == "rotate":   # rigid: strain-free, but linear FEM cannot tell it from strain
        x[ids] = centre + rotate_about(d, axis, np.full(len(d), amount))
    else:
        raise ValueError(init.kind)


def rotate_about(d, axis, angle):
    """Rotate rows of d about a unit axis by per-row angles (Rodrigues)."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return d * c + np.cross(axis, d) * s + np.outer(d @ axis, axis) * (1 - c)
