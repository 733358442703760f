"""Scenes as data: what the builder needs to make a model.

A `Scene` holds placed, validated input only (meshes, materials, effects,
initial conditions, impulses, solver settings); `fem.builder.model_arrays` turns
it into Taichi fields. `fem.scene_file` reads one from TOML, `fem.coursework`
from the coursework's files; the schema is documented in `scenes/README.md`.
"""

from dataclasses import dataclass, field, replace

import numpy as np

from fem import limits
from fem.errors import FemError
from fem.mesh import VOLUME_TOLERANCE, TetMesh, signed_volumes

# "corotational-naive" is the tempting but wrong f = -R Ke R^T (x - X): a teaching switch
# (docs/method.md), forces under a pure rotation; it always takes the one-solve step.
METHODS = ("linear", "corotational", "corotational-naive")
SOLVERS = ("pcg", "jacobi")
PRECONDITIONERS = ("auto", "two-level", "jacobi")
ROTATIONS = ("iterative", "svd")
STEPS = ("newton", "single")
# The integrator: what the step's incremental potential is built from (fem/implicit/potential.py);
# "auto" picks one per scene (fem/implicit/integrators.py: chosen)
INTEGRATORS = ("backward-euler", "bdf2", "trapezoidal")
INTEGRATOR_CHOICES = ("auto", *INTEGRATORS)


@dataclass
class Material:
    """Young's modulus E (Pa), Poisson ratio nu, density (kg/m^3)."""

    E: float
    nu: float
    density: float

    @property
    def lame(self):
        """(mu, lam), the Lame parameters, Pa."""
        E, nu = self.E, self.nu
        return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))

    @property
    def longitudinal(self):
        """lam + 2 mu, the stiffness of a compression that keeps the cross-section (the P-wave
        modulus), Pa: what a volume change costs, unbounded as nu nears 0.5."""
        mu, lam = self.lame
        return lam + 2.0 * mu

    def check(self, where):
        if not 0 < self.E <= limits.MAX_YOUNG_MODULUS:
            raise FemError(f"{where}: E must be > 0 and at most {limits.MAX_YOUNG_MODULUS:g} Pa, got {self.E}")
        if not -1.0 < self.nu < 0.5:
            raise FemError(f"{where}: nu must be in (-1, 0.5), got {self.nu}")
        if not 0 < self.density <= limits.MAX_DENSITY:
            raise FemError(f"{where}: density must be > 0 and at most {limits.MAX_DENSITY:g} kg/m^3, "
                           f"got {self.density}")


@dataclass
class Body:
    """One elastic object: its rest mesh already placed in the world."""

    name: str
    mesh: TetMesh                      # placed rest shape (world coordinates, m)
    material: Material
    method: str = "corotational"       # "linear" | "corotational"
    pinned: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # local vertex ids


@dataclass
class Selection:
    """Vertices of one body (or of all bodies, body=None) picked by a region."""

    body: int | None
    vertices: np.ndarray | None = None   # local ids (requires a body)
    sphere: tuple | None = None          # (centre (3,), radius) in world coordinates
    box: tuple | None = None             # (min (3,), max (3,)) in world coordinates


@dataclass
class Initial:
    """An initial condition applied to a selection at t = 0.

    kind: "velocity" (value: (3,) m/s, set), "spin" / "twist" (value: axis, omega rad/s),
    "stretch" / "squash" / "twist_shape" / "rotate" (value: axis, factor or angle in rad).
    """

    selection: Selection
    kind: str
    value: tuple


@dataclass
class Impulse:
    """A velocity change delta_v (m/s) added to a selection at time t (s)."""

    time: float
    selection: Selection
    delta_v: np.ndarray


@dataclass
class ContactEffect:
    """Contact between bodies and of a body with itself (fem/implicit/contact.py)."""

    distance: float = 0.01              # contact thickness d_hat, m: the barrier acts on pairs closer than this
    friction: float = 0.0               # Coulomb's coefficient mu between surfaces (>= 0)


@dataclass
class Effects:
    """Which effects a scene switches on; an effect that is off costs nothing."""

    gravity: tuple | None = None        # (gx, gy, gz) m/s^2
    ground: float | None = None         # ground plane height y (m)
    friction: float = 0.5               # Coulomb's coefficient mu on the ground (>= 0)
    contact: ContactEffect | None = None   # between bodies and within one
    stick_speed: float = 1e-3           # m/s: friction (ground's and contact's) holds below this tangential
                                        # speed (IPC's eps_v; fem/implicit/effects.py's FRICTION_SPEED)
    alpha: float = 0.0                  # Rayleigh damping D = alpha M + beta K
    beta: float = 0.0

    @property
    def damping(self):
        return self.alpha > 0 or self.beta > 0


TOLERANCE_DT = 0.02    # s: the dt at which SolverSettings' tolerances hold as set (`tolerances_at`)


@dataclass
class SolverSettings:
    dt: float = 0.02                    # s
    step: str = "newton"                # "newton": minimise the incremental potential | "single": one solve
    integrator: str = "auto"            # "trapezoidal" (second order, undamped: Newmark's average acceleration) |
                                        # "bdf2" (second order, damps fast modes) | "backward-euler" (first
                                        # order) | "auto": the trapezoidal rule, BDF2 where there is a ground
    rho_infinity: float | None = None   # the trapezoidal rule's numerical dissipation: a mode dt cannot
                                        # resolve is multiplied by -rho_infinity a step (1: none, the
                                        # conserving scheme; 0: backward Euler's); None: by the scene
                                        # (integrators.default_rho): 1, or exp(-dt / 0.5 s) with Rayleigh
                                        # damping, so that damped bodies come to rest
    max_newton: int = 20                # Newton iterations per step at most (twice that with contact between bodies)
    newton_tolerance: float = 1e-5      # per body: stop (unconverged) when a Newton iteration changes |v|_M by less
    method: str = "pcg"                 # "pcg" | "jacobi": the linear solver inside each Newton iteration
    tolerance: float = 1e-4             # per body: |grad E| / (size of the step's own terms), at dt
                                        # TOLERANCE_DT and above; below, with dt^2 (`tolerances_at`)
    max_iterations: int = 200           # linear solver iterations per Newton iteration
    jacobi_omega: float | None = None   # None: chosen from a spectral estimate
    preconditioner: str = "auto"        # PCG's: "two-level" (block Jacobi + rigid patches, fem/coarse.py) |
                                        # "jacobi" (block Jacobi) | "auto": two-level from 2000 vertices up
    rotations: str = "iterative"        # "iterative" (warm-started, SVD when inverted) | "svd"
    sleep: bool = True                  # a body at rest sleeps: no work for it until something wakes it

    def tolerances_at(self, dt):
        """(tolerance, newton_tolerance) a step of dt stops at: as set at TOLERANCE_DT and above, and
        times (dt / TOLERANCE_DT)^2 below. A solve's error per step is its tolerance times the
        step's momentum, and over the steps of a second of simulated time it adds up to as much
        whatever dt is: at a fixed 1e-4, the spinning, twisting bar's error grew from 1.7e-4 m at
        dt 0.01 s to 2.1e-3 m at 0.0025 s, 16 times finer. Following dt^2, the solve's error per step
        shrinks as the rule's own (dt^3 a step) does, and halving dt keeps the integrator's order:
        2.00, 2.40 and 2.21 on that bar down to 0.0025 s (8.4e-6 m)."""
        follow = min(1.0, (dt / TOLERANCE_DT) ** 2)
        return self.tolerance * follow, self.newton_tolerance * follow

    def check(self, where):
        if not self.dt > 0:
            raise FemError(f"{where}: dt must be > 0, got {self.dt}")
        limits.check_range(self.dt, *limits.DT_RANGE, f"{where}: dt", " s")
        if self.step not in STEPS:
            raise FemError(f"{where}: step must be one of {STEPS}, got {self.step!r}")
        if self.integrator not in INTEGRATOR_CHOICES:
            raise FemError(f"{where}: integrator must be one of {INTEGRATOR_CHOICES}, got {self.integrator!r}")
        if self.rho_infinity is not None and not 0.0 <= self.rho_infinity <= 1.0:
            raise FemError(f"{where}: rho_infinity must be in [0, 1], got {self.rho_infinity}")
        if not self.newton_tolerance > 0:
            raise FemError(f"{where}: newton_tolerance must be > 0, got {self.newton_tolerance}")
        if not self.max_newton >= 1:
            raise FemError(f"{where}: max_newton must be >= 1, got {self.max_newton}")
        if self.method not in SOLVERS:
            raise FemError(f"{where}: solver must be one of {SOLVERS}, got {self.method!r}")
        if not self.tolerance > 0:
            raise FemError(f"{where}: tolerance must be > 0, got {self.tolerance}")
        if not self.max_iterations >= 1:
            raise FemError(f"{where}: max_iterations must be >= 1, got {self.max_iterations}")
        if self.preconditioner not in PRECONDITIONERS:
            raise FemError(f"{where}: preconditioner must be one of {PRECONDITIONERS}, got {self.preconditioner!r}")
        if self.rotations not in ROTATIONS:
            raise FemError(f"{where}: rotations must be one of {ROTATIONS}, got {self.rotations!r}")
        if self.jacobi_omega is not None and not 0 < self.jacobi_omega < 2:
            raise FemError(f"{where}: jacobi_omega must be in (0, 2), got {self.jacobi_omega}")


@dataclass
class Scene:
    name: str
    bodies: list[Body]
    description: str = ""
    path: str = ""
    effects: Effects = field(default_factory=Effects)
    solver: SolverSettings = field(default_factory=SolverSettings)
    initial: list[Initial] = field(default_factory=list)
    impulses: list[Impulse] = field(default_factory=list)
    camera: dict | None = None          # {"eye": (3,), "target": (3,)}

    def side_by_side(self, gap=0.5):
        """The scene twice for comparison: bodies 0..k-1 linear on the left, k..2k-1 corotational on
        the right (shifted along +x by the scene's width plus `gap` m), with the same initial
        conditions and impulses. Body i and body i + k share local vertex numbering."""
        lo = min(b.mesh.vertices[:, 0].min() for b in self.bodies)
        hi = max(b.mesh.vertices[:, 0].max() for b in self.bodies)
        shift = np.array([hi - lo + gap, 0.0, 0.0])
        k = len(self.bodies)
        bodies = [replace(b, name=f"{b.name} (linear)", method="linear") for b in self.bodies]
        bodies += [replace(b, name=f"{b.name} (corotational)", method="corotational",
                           mesh=TetMesh(b.mesh.vertices + shift, b.mesh.tets, b.mesh.source))
                   for b in self.bodies]

        def copies(sel):
            if sel.body is None and sel.sphere is None and sel.box is None:
                return [sel]     # every body already, both copies: once each
            right = replace(sel, body=None if sel.body is None else sel.body + k,
                            sphere=None if sel.sphere is None else (sel.sphere[0] + shift, sel.sphere[1]),
                            box=None if sel.box is None else (sel.box[0] + shift, sel.box[1] + shift))
            return [sel, right]

        initial = [replace(i, selection=c) for i in self.initial for c in copies(i.selection)]
        impulses = [replace(i, selection=c) for i in self.impulses for c in copies(i.selection)]
        camera = None
        if self.camera is not None:   # same view direction, centred between the copies, backed off
            target = np.asarray(self.camera["target"]) + shift / 2
            offset = np.asarray(self.camera["eye"]) - self.camera["target"]
            distance = np.linalg.norm(offset)
            camera = {"eye": target + offset * (1 + shift[0] / max(distance, 1e-9)), "target": target}
        return replace(self, name=f"{self.name} (linear vs corotational)", bodies=bodies,
                       initial=initial, impulses=impulses, camera=camera)

    def with_method(self, method):
        """A copy with every body switched to `method` ("linear" | "corotational")."""
        bodies = [replace(b, method=method) for b in self.bodies]
        return replace(self, bodies=bodies)


def place_mesh(mesh, position=(0, 0, 0), rotation=(1, 0, 0, 0), scale=1.0):
    """Re-centre a mesh on its volume-weighted centre of mass, scale, rotate, translate.

    rotation is a quaternion (w, x, y, z), normalised here; this is the coursework's
    placement convention, so both scene formats agree.
    """
    X = mesh.vertices
    vol = signed_volumes(X, mesh.tets)
    centres = X[mesh.tets].mean(axis=1)
    com = (vol[:, None] * centres).sum(axis=0) / vol.sum()
    R = quaternion_matrix(rotation)
    placed = (scale * (X - com)) @ R.T + np.asarray(position, float)
    return TetMesh(placed, mesh.tets.copy(), mesh.source)


def quaternion_matrix(q):
    q = np.asarray(q, float)
    q = q / np.abs(q).max()       # first: the norm of (1e300, 0, 0, 1e300) would overflow to inf
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def axis_angle_quaternion(axis, angle_deg):
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    h = np.radians(angle_deg) / 2
    return (np.cos(h), *(np.sin(h) * a))


# ---------------------------------------------------------------- regions

def select_vertices(sel, bodies, where):
    """[(body index, local vertex ids)] picked by a selection; an empty pick is an error."""
    picks = []
    for i, body in enumerate(bodies):
        if sel.body is not None and sel.body != i:
            continue
        X = body.mesh.vertices
        ids = np.arange(len(X))
        if sel.vertices is not None:
            ids = sel.vertices
        elif sel.sphere is not None:
            c, r = sel.sphere
            ids = ids[np.linalg.norm(X - c, axis=1) <= r]
        elif sel.box is not None:
            lo, hi = sel.box
            ids = ids[np.all((X >= lo) & (X <= hi), axis=1)]
        if len(ids):
            picks.append((i, ids))
    if not picks:
        raise FemError(f"{where}: the region selects no vertex")
    return picks


def check_placed(vertices, tets, where):
    """FemError when a placed mesh is too far away (fem.limits.MAX_COORDINATE), or so far for
    its size that its tets lose their volume in float64 (a body 1 m across placed at 1e16 m).
    (Here, beside place_mesh, not in fem.limits: it needs fem.mesh, which imports fem.limits.)"""
    farthest = float(np.abs(vertices).max())
    if not farthest <= limits.MAX_COORDINATE:
        raise FemError(f"{where}: a vertex is placed {farthest:.3g} m from the origin, "
                       f"more than {limits.MAX_COORDINATE:g} m (check position and scale)")
    side = float(np.ptp(vertices, axis=0).max())
    volumes = np.abs(signed_volumes(vertices, tets))
    if not side > 0 or not (volumes > VOLUME_TOLERANCE * side**3).all():
        raise FemError(f"{where}: placed at this position and scale, tets lose their volume in "
                       f"floating point (body {side:.3g} m across, {farthest:.3g} m from the origin)")


# Machine epsilon of each precision, and the share of it a model may use up: a coordinate's
# rounding must stay below RESOLVED_EDGE of the smallest edge (the hard cases' 0.5 mm sliver at
# 24.5 m uses 0.6 % of it in f32), and mu must stay at least ten roundings of lam (lam / mu
# below RESOLVED / epsilon: nu up to 0.4999994 in f32; the hard cases' 0.49995 is 1e4).
EPSILON = {"f32": float(np.finfo(np.float32).eps), "f64": float(np.finfo(np.float64).eps)}
RESOLVED = 0.1
RESOLVED_EDGE = 1e-2


def check_precision(scene, precision: str):
    """FemError for a scene that `precision` ("f32" or "f64") cannot represent: a body so far
    from the origin that its coordinates round by more than RESOLVED_EDGE of its smallest edge
    (1 cm tets at 1e5 m in f32: a body at rest reports a volume ratio of 1.56), or nu so close
    to 0.5 that lam drowns mu (total energy 50 J -> 9e5 J in 20 steps)."""
    epsilon = EPSILON[precision]
    for body in scene.bodies:
        where = f"{scene.path or scene.name}: body {body.name!r}"
        vertices, tets = body.mesh.vertices, body.mesh.tets
        edges = np.linalg.norm(vertices[tets[:, [0, 0, 0, 1, 1, 2]]] - vertices[tets[:, [1, 2, 3, 2, 3, 3]]], axis=2)
        farthest, shortest = float(np.abs(vertices).max()), float(edges.min())
        if farthest * epsilon > RESOLVED_EDGE * shortest:
            raise FemError(f"{where}: {farthest:.3g} m from the origin, {precision} rounds coordinates to "
                           f"{farthest * epsilon:.2g} m, too coarse for its {shortest:.3g} m edges; place it "
                           f"within {RESOLVED_EDGE * shortest / epsilon:.3g} m of the origin, or use precision f64")
        nu = body.material.nu
        if 2 * nu / (1 - 2 * nu) * epsilon > RESOLVED:
            highest = 0.5 * (RESOLVED / epsilon) / (1 + RESOLVED / epsilon)
            digits = int(-np.log10(0.5 - highest)) + 2
            raise FemError(f"{where}: nu = {nu!r} makes lam {2 * nu / (1 - 2 * nu):.3g} times mu, more than "
                           f"{precision} can add mu to; use nu <= {np.floor(highest * 10**digits) / 10**digits}"
                           + (" or precision f64" if precision == "f32" else ""))
