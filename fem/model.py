"""Model (what never changes in a run, except by a live edit) and State (what does), as Taichi fields.

`model_arrays(scene)` (fem/builder.py) concatenates every body into one set of arrays, so
a single kernel launch covers all bodies; per-body Lame parameters and method flags,
read through each tet's body, let each body keep its own material and method. The Model
keeps no reference to the Scene it was built from.

Fields are sized to a `Capacity`, not to the mesh: kernels loop over the counts in use
(`vertex_count`, `tet_count`, `body_count`), so one Model, with every kernel compiled
for it, serves any later scene that fits (fem/pool.py).
"""

from dataclasses import dataclass

import numpy as np
import taichi as ti

from fem.elastic import edge_matrix
from fem.scene import METHODS, Material


@dataclass
class BodyInfo:
    """Where a body lives in the model's arrays, and its current material and method."""

    name: str
    vertices: slice            # global vertex ids of this body
    tets: slice                # global tet ids of this body
    rest_volume: float         # m^3
    size: float                # diagonal of its rest bounding box, m
    mass: float                # kg
    surface: np.ndarray        # (k, 3) global vertex ids of its boundary triangles
    material: Material
    method: str                # "linear" | "corotational"


@dataclass(frozen=True)
class Capacity:
    """How many vertices, tets and bodies a Model's fields hold: each count rounded up to an
    eighth of a power of two (at most 12.5 % unused), so similar meshes share a size."""

    vertices: int
    tets: int
    bodies: int

    @staticmethod
    def rounded(count, smallest):
        size = max(count, smallest)
        step = max(1, (1 << (size - 1).bit_length()) // 8)
        return -(-size // step) * step

    @classmethod
    def fitting(cls, n_vertices, n_tets, n_bodies):
        # per-body fields are tiny: room for 32 bodies lets scenes of 1 to 32 bodies share kernels
        return cls(cls.rounded(n_vertices, 1024), cls.rounded(n_tets, 4096), cls.rounded(n_bodies, 32))


@ti.data_oriented
class Model:
    """Rest shape, per-tet constants, masses and materials of every body.

    Fields (n vertices, m tets, used of the capacity; float is f32 or f64 as chosen at fem.init):
        rest_positions (n, 3)   X, m
        tets (m, 4)             vertex ids, positively oriented
        Bm (m, 3x3)             inverse rest edge matrix, 1/m
        rest_volume (m,)        W, m^3
        body_mu, body_lam (bodies,)   Lame parameters, Pa (per tet: mu(e), lam(e))
        body_method (bodies,)   0 linear, 1 corotational, 2 the naive variant (NAIVE) (per tet: method(e))
        mass (n,)               lumped mass, kg
        free (n,)               0 for pinned vertices, else 1
        vertex_body (n,), tet_body (m,)   the body each belongs to
        adjacency_start (n+1,), adjacency (4m,)   vertex -> corner slots (4*tet + corner),
                                 so per-vertex sums gather instead of racing on atomics
        vertex_count, tet_count, body_count ()    n, m and the number of bodies
    `version` counts live edits (method, material): what is derived from them checks it.
    """

    def __init__(self, capacity):
        n, m, nb = capacity.vertices, capacity.tets, capacity.bodies
        self.capacity = capacity
        self.rest_positions = ti.Vector.field(3, float, n)
        self.tets = ti.Vector.field(4, ti.i32, m)
        self.Bm = ti.Matrix.field(3, 3, float, m)
        self.rest_volume = ti.field(float, m)
        self.body_mu = ti.field(float, nb)
        self.body_lam = ti.field(float, nb)
        self.body_method = ti.field(ti.i32, nb)
        self.mass = ti.field(float, n)
        self.free = ti.field(float, n)
        self.vertex_body = ti.field(ti.i32, n)
        self.tet_body = ti.field(ti.i32, m)
        self.adjacency_start = ti.field(ti.i32, n + 1)
        self.adjacency = ti.field(ti.i32, 4 * m)
        self.vertex_count = ti.field(ti.i32, ())
        self.tet_count = ti.field(ti.i32, ())
        self.body_count = ti.field(ti.i32, ())
        assert nb >= 1

    def load(self, bodies, X, T, mass, free):
        """Fill the fields with a scene's bodies, rest positions X (n, 3), tets T (m, 4),
        lumped masses (n,) and free flags (n,) (fem.builder.model_arrays)."""
        n, m = len(X), len(T)
        self.bodies = bodies
        self.n_vertices, self.n_tets = n, m
        self.rest_positions_np, self.tets_np, self.mass_np, self.free_np = X, T, mass, free
        self.surface = np.concatenate([b.surface for b in bodies])
        self.tet_body_np = np.concatenate([np.full(b.tets.stop - b.tets.start, i, np.int32)
                                           for i, b in enumerate(bodies)])
        self.vertex_body_np = np.concatenate([np.full(b.vertices.stop - b.vertices.start, i, np.int32)
                                              for i, b in enumerate(bodies)])
        self.has_pins = bool((free == 0).any())
        Dm = np.stack([X[T[:, k]] - X[T[:, 3]] for k in range(3)], axis=2)
        order = np.argsort(T.ravel(), kind="stable")
        start = np.searchsorted(T.ravel()[order], np.arange(n + 1))

        self.vertex_count[None], self.tet_count[None], self.body_count[None] = n, m, len(bodies)
        rows, padded = self.capacity.vertices, self.padded      # one kernel per kind of row, not per field
        self._load_vertices(padded(X, rows), padded(mass, rows), padded(free, rows),
                            padded(self.vertex_body_np, rows, np.int32),
                            padded(start, rows + 1, np.int32, pad=start[-1]))
        rows = self.capacity.tets
        self._load_tets(padded(T, rows, np.int32), padded(np.linalg.inv(Dm), rows),
                        padded(np.abs(np.linalg.det(Dm)) / 6, rows), padded(self.tet_body_np, rows, np.int32),
                        padded(order.reshape(-1, 4), rows, np.int32))
        self.version = 0
        for i, b in enumerate(bodies):
            self.set_material(i, b.material)
            self.set_method(i, b.method)

    @staticmethod
    def write(field, values, pad=0):
        """field <- values (numpy, the first len(values) rows); the rows beyond get `pad`."""
        values = np.asarray(values)
        field.from_numpy(Model.padded(values, field.shape[0], values.dtype, pad))

    @staticmethod
    def padded(values, rows, dtype=np.float64, pad=0):
        """values (numpy) as `rows` rows of `dtype`, the rows beyond len(values) filled with `pad`."""
        full = np.full((rows,) + np.shape(values)[1:], pad, dtype=dtype)
        full[:len(values)] = values
        return full

    @ti.kernel
    def _load_vertices(self, X: ti.types.ndarray(), mass: ti.types.ndarray(), free: ti.types.ndarray(),
                       body: ti.types.ndarray(), start: ti.types.ndarray()):
        for i in range(X.shape[0]):
            self.rest_positions[i] = ti.Vector([X[i, 0], X[i, 1], X[i, 2]])
            self.mass[i], self.free[i], self.vertex_body[i] = mass[i], free[i], body[i]
        for i in range(start.shape[0]):
            self.adjacency_start[i] = start[i]

    @ti.kernel
    def _load_tets(self, T: ti.types.ndarray(), Bm: ti.types.ndarray(), volume: ti.types.ndarray(),
                   body: ti.types.ndarray(), slots: ti.types.ndarray()):
        for e in range(T.shape[0]):
            for k in ti.static(range(4)):
                self.tets[e][k] = T[e, k]
                self.adjacency[4 * e + k] = slots[e, k]
            for i, j in ti.static(ti.ndrange(3, 3)):
                self.Bm[e][i, j] = Bm[e, i, j]
            self.rest_volume[e], self.tet_body[e] = volume[e], body[e]

    # ------------------------------------------------------------ live edits: the one path

    def set_material(self, body, material):
        """A new Material (E Pa, nu; density stays) for one body."""
        info = self.bodies[body]
        material = Material(material.E, material.nu, info.material.density)
        material.check(f"body {info.name!r}")
        info.material = material
        self._set_body(body, *material.lame, METHODS.index(info.method))
        self.version += 1

    def set_method(self, body, method):
        """Switch one body between "linear", "corotational" and "corotational-naive" (next step)."""
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        info = self.bodies[body]
        info.method = method
        self._set_body(body, *info.material.lame, METHODS.index(method))
        self.version += 1

    @ti.kernel
    def _set_body(self, body: ti.i32, mu: float, lam: float, method: ti.i32):
        self.body_mu[body], self.body_lam[body], self.body_method[body] = mu, lam, method

    @ti.func
    def mu(self, e):
        """Lame's mu of tet e's body, Pa."""
        return self.body_mu[self.tet_body[e]]

    @ti.func
    def lam(self, e):
        """Lame's lambda of tet e's body, Pa."""
        return self.body_lam[self.tet_body[e]]

    @ti.func
    def edges(self, x: ti.template(), e):
        """Ds of tet e for the vertex values x (positions, velocities or directions)."""
        t = self.tets[e]
        return edge_matrix(x[t[0]], x[t[1]], x[t[2]], x[t[3]])

    @ti.func
    def method(self, e):
        """0 linear, 1 corotational, 2 naive (fem.scene.METHODS) for tet e's body."""
        return self.body_method[self.tet_body[e]]

    @property
    def any_corotational(self):
        """Some body needs rotations (the naive variant too)."""
        return any(b.method != "linear" for b in self.bodies)

    @property
    def any_naive(self):
        return any(b.method == "corotational-naive" for b in self.bodies)

    def stiff(self, dt, shear=False):
        """Per body, whether it may be too stiff for dt to follow: the step's test (Safeguards.stiff_turn,
        (lam + 2 mu) dt^2 r >= M) at the largest radius of gyration it allows, r = 2 L (L the
        body's size); shear: with 2 mu for lam + 2 mu (a nearly incompressible jelly is stiff, not
        in shear). Returns (bodies,) bool."""
        return np.array([(2.0 * b.material.lame[0] if shear else b.material.longitudinal) * dt * dt * 2.0 * b.size
                         >= b.mass for b in self.bodies], bool)

    def any_stiff(self, dt, shear=False):
        """Some body may be too stiff for dt to follow (`stiff`): a scene with none launches (and
        compiles) nothing for it."""
        return bool(self.stiff(dt, shear).any())

    def body_floor(self, relative, dt, volume=0.0):
        """Per body, the square of `relative` times dt k L^2 (N s): the impulse over a step of
        the body's stiffness k times its cross-section, the size of the round-off in its elastic
        forces (positions carry round-off relative to their size L whatever the strain).
        Below it a gradient is round-off. k is E, or `volume` times lam + 2 mu where that is
        more: the volume term's own round-off, which outgrows E's as nu nears 0.5. Returns
        (bodies,) float64."""
        return np.array([(relative * dt * max(b.material.E, volume * b.material.longitudinal) * b.size ** 2) ** 2
                         for b in self.bodies])

    def body_quiet(self, relative, dt):
        """Per body, the energy round-off of `relative` gives it at rest (J): a strain of
        `relative` everywhere, E V relative^2, and a motion of `relative` of its size L in a step,
        m (relative L / dt)^2. A body at rest with no gravity has terms of size 0, and its energy
        wanders by 1e-28 J (float64) from one step to the next: that is no rise."""
        return np.array([b.material.E * b.rest_volume * relative ** 2 + b.mass * (relative * b.size / dt) ** 2
                         for b in self.bodies])

    def body_speed_floor(self, relative, dt):
        """Per body, m (relative L / dt)^2 (J): twice the kinetic energy of the body moving
        `relative` of its size L in a step. Below it a velocity change is round-off."""
        return np.array([b.mass * (relative * b.size / dt) ** 2 for b in self.bodies])


@ti.data_oriented
class State:
    """Positions x and velocities v (capacity, 3), of which the model's first n are in use (m, m/s)."""

    def __init__(self, capacity):
        self.x = ti.Vector.field(3, float, capacity)
        self.v = ti.Vector.field(3, float, capacity)

    def load(self, x, v):
        rows = self.x.shape[0]
        self._load(Model.padded(x, rows), Model.padded(v, rows))

    @ti.kernel
    def take(self, other: ti.template()):
        """x, v <- other's: a step's result is copied in, not swapped in, so that every kernel
        sees the same State each step and compiles once, not once for each of two."""
        for i in range(self.x.shape[0]):
            self.x[i], self.v[i] = other.x[i], other.v[i]

    @ti.kernel
    def _load(self, x: ti.types.ndarray(), v: ti.types.ndarray()):
        for i in range(x.shape[0]):
            self.x[i] = ti.Vector([x[i, 0], x[i, 1], x[i, 2]])
            self.v[i] = ti.Vector([v[i, 0], v[i, 1], v[i, 2]])
