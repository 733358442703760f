"""Model (what never changes in a run) and State (what does), as Taichi fields.

`build_model(scene)` concatenates every body into one set of fields, so a single
kernel launch covers all bodies; per-tet Lame parameters and a per-tet method flag
let each body keep its own material and method.
"""

from dataclasses import dataclass

import numpy as np
import taichi as ti

from fem.mesh import boundary_faces
from fem.scene import select_vertices


@dataclass
class BodyInfo:
    """Where a body lives in the model's arrays."""

    name: str
    vertices: slice            # global vertex ids of this body
    tets: slice                # global tet ids of this body
    rest_volume: float         # m^3
    surface: np.ndarray        # (k, 3) global vertex ids of its boundary triangles


@ti.data_oriented
class Model:
    """Rest shape, per-tet constants, masses and materials of every body.

    Fields (n vertices, m tets; float is f32 or f64 as chosen at fem.init):
        rest_positions (n, 3)   X, m
        tets (m, 4)             vertex ids, positively oriented
        Bm (m, 3x3)             inverse rest edge matrix, 1/m
        rest_volume (m,)        W, m^3
        mu, lam (m,)            Lame parameters, Pa
        corotational (m,)       1 where the tet's body uses corotational FEM
        mass (n,)               lumped mass, kg
        free (n,)               0 for pinned vertices, else 1
        adjacency_start (n+1,), adjacency (4m,)   vertex -> corner slots (4*tet + corner),
                                 so per-vertex sums gather instead of racing on atomics
    """

    def __init__(self, scene):
        meshes = [b.mesh for b in scene.bodies]
        self.scene = scene
        self.n_vertices = sum(len(m.vertices) for m in meshes)
        self.n_tets = sum(len(m.tets) for m in meshes)
        X = np.concatenate([m.vertices for m in meshes])
        v_off = np.cumsum([0] + [len(m.vertices) for m in meshes])
        t_off = np.cumsum([0] + [len(m.tets) for m in meshes])
        T = np.concatenate([m.tets + o for m, o in zip(meshes, v_off)]).astype(np.int32)
        self.bodies = []
        for i, b in enumerate(scene.bodies):
            surface = boundary_faces(b.mesh.tets) + v_off[i]
            self.bodies.append(BodyInfo(b.name, slice(v_off[i], v_off[i + 1]),
                                        slice(t_off[i], t_off[i + 1]), 0.0, surface.astype(np.int32)))
        self.surface = np.concatenate([b.surface for b in self.bodies])
        self.tet_body = np.repeat(np.arange(len(meshes)), np.diff(t_off)).astype(np.int32)
        self.vertex_body = np.repeat(np.arange(len(meshes)), np.diff(v_off)).astype(np.int32)
        self.rest_positions_np = X
        self.tets_np = T

        Dm = np.stack([X[T[:, k]] - X[T[:, 3]] for k in range(3)], axis=2)
        W = np.abs(np.linalg.det(Dm)) / 6
        for info in self.bodies:
            info.rest_volume = float(W[info.tets].sum())
        density = np.array([b.material.density for b in scene.bodies])[self.tet_body]
        mass = np.zeros(self.n_vertices)
        np.add.at(mass, T.ravel(), np.repeat(density * W / 4, 4))
        free = (mass > 0).astype(float)          # a vertex in no tet has no mass: keep it still
        for i, b in enumerate(scene.bodies):
            free[b.pinned + v_off[i]] = 0.0
        order = np.argsort(T.ravel(), kind="stable")
        start = np.searchsorted(T.ravel()[order], np.arange(self.n_vertices + 1))
        self.has_pins = bool((free == 0).any())

        n, m = self.n_vertices, self.n_tets
        self.rest_positions = ti.Vector.field(3, float, n)
        self.tets = ti.Vector.field(4, ti.i32, m)
        self.Bm = ti.Matrix.field(3, 3, float, m)
        self.rest_volume = ti.field(float, m)
        self.mu = ti.field(float, m)
        self.lam = ti.field(float, m)
        self.corotational = ti.field(ti.i32, m)
        self.mass = ti.field(float, n)
        self.free = ti.field(float, n)
        self.adjacency_start = ti.field(ti.i32, n + 1)
        self.adjacency = ti.field(ti.i32, 4 * m)

        self.rest_positions.from_numpy(X)
        self.tets.from_numpy(T)
        self.Bm.from_numpy(np.linalg.inv(Dm))
        self.rest_volume.from_numpy(W)
        self.mass.from_numpy(mass)
        self.free.from_numpy(free)
        self.adjacency_start.from_numpy(start.astype(np.int32))
        self.adjacency.from_numpy(order.astype(np.int32))
        self.material_version = 0
        for i, b in enumerate(scene.bodies):
            self.set_material(i, b.material.E, b.material.nu)
            self.set_method(i, b.method)
        self.mass_np = mass

    # ------------------------------------------------------------ per-body settings

    def set_material(self, body, E, nu):
        """Young's modulus E (Pa) and Poisson ratio nu for one body's tets."""
        self.material_version += 1
        self.scene.bodies[body].material.E = E
        self.scene.bodies[body].material.nu = nu
        s = self.bodies[body].tets
        mu = E / (2 * (1 + nu))
        lam = E * nu / ((1 + nu) * (1 - 2 * nu))
        self._fill(self.mu, s.start, s.stop, mu)
        self._fill(self.lam, s.start, s.stop, lam)

    def set_method(self, body, method):
        """Switch one body between "linear" and "corotational" (takes effect next step)."""
        self.scene.bodies[body].method = method
        s = self.bodies[body].tets
        self._fill_int(self.corotational, s.start, s.stop, int(method == "corotational"))

    @property
    def any_corotational(self):
        return any(b.method == "corotational" for b in self.scene.bodies)

    @ti.kernel
    def _fill(self, f: ti.template(), start: ti.i32, stop: ti.i32, value: float):
        for e in range(start, stop):
            f[e] = value

    @ti.kernel
    def _fill_int(self, f: ti.template(), start: ti.i32, stop: ti.i32, value: ti.i32):
        for e in range(start, stop):
            f[e] = value

    # ------------------------------------------------------------ initial state

    def initial_state(self):
        """(positions, velocities) at t = 0, (n, 3) each, with the scene's initial conditions applied."""
        x = self.rest_positions_np.copy()
        v = np.zeros_like(x)
        offsets = [b.vertices.start for b in self.bodies]
        for init in self.scene.initial:
            for body, ids in select_vertices(init.selection, self.scene.bodies, "initial condition"):
                g = ids + offsets[body]
                apply_initial(init, x, v, g, self.mass_np[g])
        free = self.free.to_numpy()[:, None]
        return x, v * free


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


@ti.data_oriented
class State:
    """Positions x (n, 3) in m and velocities v (n, 3) in m/s."""

    def __init__(self, n):
        self.x = ti.Vector.field(3, float, n)
        self.v = ti.Vector.field(3, float, n)

    def load(self, x, v):
        self.x.from_numpy(x)
        self.v.from_numpy(v)
