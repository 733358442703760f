"""Scenes as data: what the builder needs to make a model, read from TOML or coursework files.

A `Scene` holds placed, validated input only (meshes, materials, effects,
initial conditions, impulses, solver settings); `fem.model.build_model` turns
it into Taichi fields. The schema is documented in `scenes/README.md`.
"""

import copy
import difflib
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from fem.errors import FemError
from fem.mesh import TetMesh, signed_volumes

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
METHODS = ("linear", "corotational")
SOLVERS = ("pcg", "jacobi")
ROTATIONS = ("iterative", "svd")
STEPS = ("newton", "single")


@dataclass
class Material:
    """Young's modulus E (Pa), Poisson ratio nu, density (kg/m^3)."""

    E: float
    nu: float
    density: float

    def check(self, where):
        if not self.E > 0:
            raise FemError(f"{where}: E must be > 0, got {self.E}")
        if not -1.0 < self.nu < 0.5:
            raise FemError(f"{where}: nu must be in (-1, 0.5), got {self.nu}")
        if not self.density > 0:
            raise FemError(f"{where}: density must be > 0, got {self.density}")


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
class Effects:
    """Which effects a scene switches on; an effect that is off costs nothing."""

    gravity: tuple | None = None        # (gx, gy, gz) m/s^2
    ground: float | None = None         # ground plane height y (m)
    friction: float = 0.5               # tangential velocity removed on contact, 0..1
    alpha: float = 0.0                  # Rayleigh damping D = alpha M + beta K
    beta: float = 0.0

    @property
    def damping(self):
        return self.alpha > 0 or self.beta > 0


@dataclass
class SolverSettings:
    dt: float = 0.02                    # s
    step: str = "newton"                # "newton": minimise the incremental potential | "single": one solve
    max_newton: int = 20                # Newton iterations per step at most
    newton_tolerance: float = 1e-3      # per body: stop when a Newton iteration changes |v|_M by less
    method: str = "pcg"                 # "pcg" | "jacobi": the linear solver inside each Newton iteration
    tolerance: float = 1e-4             # per body: |grad E| / (size of the step's own terms)
    max_iterations: int = 200           # linear solver iterations per Newton iteration
    jacobi_omega: float | None = None   # None: chosen from a spectral estimate
    rotations: str = "iterative"        # "iterative" (warm-started, SVD when inverted) | "svd"

    def check(self, where):
        if not self.dt > 0:
            raise FemError(f"{where}: dt must be > 0, got {self.dt}")
        if self.step not in STEPS:
            raise FemError(f"{where}: step must be one of {STEPS}, got {self.step!r}")
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
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
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


# ---------------------------------------------------------------- finding scenes

def builtin_scenes():
    """{name: description} of every scene file shipped in scenes/."""
    out = {}
    for path in sorted(SCENES_DIR.glob("*.toml")):
        with open(path, "rb") as f:
            out[path.stem] = tomllib.load(f).get("description", "")
    return out


def load_scene(ref, overrides=None):
    """A Scene from a built-in name, a .toml path, a coursework *-scene.txt path, or a mesh file.

    A mesh file (a surface: .obj .stl .ply .off, tetrahedralised and cached; or tets:
    .mesh .msh .vtk .vtu .node .ele) is a one-body scene with the defaults of
    `assets.mesh_file_scene`.
    overrides: ["key.path=value", ...] applied to a TOML scene before it is read,
    e.g. "solver.dt=0.01" or "body.soft.mesh.cells=[8, 8, 8]" (a body by name or index,
    or * for every body); paths in them are relative to the current folder.
    """
    from assets import MESH_FILE_SUFFIXES, mesh_file_scene

    path = Path(ref)
    suffix = path.suffix.lower()
    if suffix == ".txt":
        from fem.coursework import read_coursework_scene
        if overrides:
            raise FemError(f"{path}: --set works on TOML scenes and mesh files only")
        return read_coursework_scene(path)
    if suffix in MESH_FILE_SUFFIXES:
        if not path.is_file():
            raise FemError(f"{path}: no such mesh file")
        return read_toml_scene(path, overrides or [], data=mesh_file_scene(path))
    if suffix != ".toml":
        builtin = SCENES_DIR / f"{ref}.toml"
        if not builtin.exists():
            if path.is_file():
                known = ", ".join([".toml", "-scene.txt", *MESH_FILE_SUFFIXES])
                raise FemError(f"{path}: not a scene or mesh file (known: {known})")
            names = list(builtin_scenes())
            hint = difflib.get_close_matches(str(ref), names, n=1)
            also = f" (did you mean {hint[0]!r}?)" if hint else f"; built-in scenes: {', '.join(names)}"
            raise FemError(f"{ref}: no such scene file or built-in scene{also}")
        path = builtin
    return read_toml_scene(path, overrides or [])


# ---------------------------------------------------------------- TOML reading

class Table:
    """A TOML table that checks types and remembers which keys were read.

    `done()` turns any key left unread into an error naming it and the closest
    valid key, so a typo never passes silently.
    """

    def __init__(self, data, where, known):
        if not isinstance(data, dict):
            raise FemError(f"{where}: expected a table, got {type(data).__name__}")
        self.data, self.where, self.known = data, where, known
        unknown = [k for k in data if k not in known]
        if unknown:
            hint = difflib.get_close_matches(unknown[0], known, n=1)
            also = f" (did you mean {hint[0]!r}?)" if hint else f"; valid keys: {', '.join(known)}"
            raise FemError(f"{where}: unknown key {unknown[0]!r}{also}")

    def __contains__(self, key):
        return key in self.data

    def key_path(self, key):
        """Where a key sits, for messages: 'x.toml: solver.dt', 'x.toml: body[0].material.E'."""
        return f"{self.where}.{key}" if ": " in self.where else f"{self.where}: {key}"

    def get(self, key, kind, default=None):
        if key not in self.data:
            return default
        value = self.data[key]
        return check_type(value, kind, self.key_path(key))

    def require(self, key, kind):
        if key not in self.data:
            raise FemError(f"{self.where}: missing key {key!r}")
        return self.get(key, kind)

    def table(self, key, known):
        return Table(self.data.get(key, {}), self.key_path(key), known)


def check_type(value, kind, where):
    """Validate a TOML value: kind is 'float', 'int', 'str', 'bool', 'vec3', 'vec4', 'ints' or 'table'."""
    def fail(expected):
        raise FemError(f"{where}: expected {expected}, got {value!r}")

    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            fail("a number")
        if not np.isfinite(value):
            fail("a finite number")
        return float(value)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            fail("an integer")
        return value
    if kind == "str":
        return value if isinstance(value, str) else fail("a string")
    if kind == "bool":
        return value if isinstance(value, bool) else fail("true or false")
    if kind in ("vec3", "vec4"):
        n = int(kind[-1])
        if not (isinstance(value, list) and len(value) == n):
            fail(f"a list of {n} numbers")
        return np.array([check_type(v, "float", where) for v in value])
    if kind == "ints":
        if not isinstance(value, list) or not value:
            fail("a non-empty list of integers")
        return np.array([check_type(v, "int", where) for v in value], dtype=np.int64)
    if kind == "table":
        return value if isinstance(value, dict) else fail("a table")
    raise ValueError(kind)


def apply_override(data, text):
    """Set one "a.b.c=value" in the raw TOML data; value is TOML (a bare word counts as a string).

    A mesh path in it (a `file` or `surface` key) is relative to the current folder,
    where the user typed it, not to the scene file's folder.
    """
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise FemError(f"--set {text!r}: expected KEY=VALUE, e.g. solver.dt=0.01")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    node, parts = data, key.strip().split(".")
    for i, part in enumerate(parts[:-1]):
        if isinstance(node, list) and part == "*":   # every entry: body.*.scale=2
            for entry in node:
                apply_override(entry, f"{'.'.join(parts[i + 1:])}={raw}")
            return
        if isinstance(node, list):
            names = [b.get("name") for b in node]
            if part in names:
                node = node[names.index(part)]
            elif part.isdigit() and int(part) < len(node):
                node = node[int(part)]
            else:
                raise FemError(f"--set {key}: no entry {part!r} in {'.'.join(parts[:i]) or 'scene'}")
        else:
            node = node.setdefault(part, {})
    if not isinstance(node, dict):
        raise FemError(f"--set {key}: {'.'.join(parts[:-1])} is not a table")
    if isinstance(value, dict):                   # body.0.mesh={file="my.mesh"}
        for name in ("file", "surface"):
            if isinstance(value.get(name), str) and value[name]:
                value[name] = str(Path(value[name]).expanduser().absolute())
    elif parts[-1] in ("file", "surface") and isinstance(value, str) and value:
        value = str(Path(value).expanduser().absolute())
    node[parts[-1]] = value


def read_toml_scene(path, overrides=(), data=None):
    """The Scene in a TOML file, with overrides ["key.path=value", ...] applied.

    data: the scene's raw TOML data when it does not come from reading `path` (a
    mesh file's one-body scene); `path` then names it in messages. A mistake that
    only an override brings in is blamed on that override, not on the file.
    """
    path = Path(path)
    if data is None:
        if not path.is_file():
            raise FemError(f"{path}: no such scene file")
        try:
            with open(path, "rb") as f:
                data = tomllib.load(f)
        except tomllib.TOMLDecodeError as e:
            raise FemError(f"{path}: not valid TOML: {e}") from None
        except (OSError, UnicodeDecodeError) as e:
            raise FemError(f"{path}: cannot read: {e}") from None
    if overrides:
        def overridden(texts):
            changed = copy.deepcopy(data)
            for text in texts:
                apply_override(changed, text)
            return read_toml_scene(path, (), changed)

        try:
            return overridden(overrides)
        except FemError as error:
            if str(error).startswith("--set "):       # apply_override already names it
                raise
            try:
                read_toml_scene(path, (), copy.deepcopy(data))
            except FemError:
                raise error from None             # the file is wrong on its own
            for count in range(1, len(overrides) + 1):
                try:
                    overridden(overrides[:count])
                except FemError as culprit:
                    message = str(culprit).removeprefix(f"{path}: ")
                    if message.startswith("--set "):
                        raise
                    scene = f"built-in scene {path.stem}" if path.parent == SCENES_DIR else f"scene {path}"
                    raise type(culprit)(f"--set {overrides[count - 1]}: {message} ({scene})") from None
            raise
    top = Table(data, str(path), ["name", "description", "body", "effects", "solver",
                                  "initial", "impulse", "camera"])
    bodies_raw = data.get("body")
    if not isinstance(bodies_raw, list) or not bodies_raw:
        raise FemError(f"{path}: a scene needs at least one [[body]] table")
    bodies = [read_body(b, i, path) for i, b in enumerate(bodies_raw)]
    names = [b.name for b in bodies]
    if len(set(names)) != len(names):
        raise FemError(f"{path}: body names must be unique, got {names}")

    scene = Scene(
        name=top.get("name", "str", path.stem),
        description=top.get("description", "str", ""),
        path=str(path),
        bodies=bodies,
        effects=read_effects(top.table("effects", ["gravity", "ground", "damping"]), path),
        solver=read_solver(top.table("solver", ["dt", "step", "max_newton", "newton_tolerance", "method", "tolerance",
                                                 "max_iterations", "jacobi_omega", "rotations"])),
    )
    scene.solver.check(f"{path}: solver")
    for i, raw in enumerate(list_of_tables(data, "initial", path)):
        scene.initial.append(read_initial(raw, f"{path}: initial[{i}]", bodies))
    for i, raw in enumerate(list_of_tables(data, "impulse", path)):
        scene.impulses.append(read_impulse(raw, f"{path}: impulse[{i}]", bodies))
    if "camera" in data:
        cam = top.table("camera", ["eye", "target"])
        scene.camera = {"eye": cam.require("eye", "vec3"), "target": cam.require("target", "vec3")}
    return scene


def list_of_tables(data, key, path):
    raw = data.get(key, [])
    if not isinstance(raw, list) or not all(isinstance(t, dict) for t in raw):
        raise FemError(f"{path}: {key} must be written as [[{key}]] tables")
    return raw


def read_body(raw, index, path):
    from assets import build_mesh

    where = f"{path}: body[{index}]"
    t = Table(raw, where, ["name", "mesh", "material", "method", "position", "rotation",
                           "rotation_axis_angle", "scale", "fixed", "pin"])
    name = t.get("name", "str", f"body{index}")
    where = f"{path}: body {name!r}"
    mesh = build_mesh(t.require("mesh", "table"), path.parent, f"{where}.mesh")
    m = t.table("material", ["E", "nu", "density"])
    material = Material(m.require("E", "float"), m.require("nu", "float"), m.get("density", "float", 1000.0))
    material.check(f"{where}.material")
    method = t.get("method", "str", "corotational")
    if method not in METHODS:
        raise FemError(f"{where}.method: must be one of {METHODS}, got {method!r}")
    rotation = t.get("rotation", "vec4", np.array([1.0, 0, 0, 0]))
    if "rotation_axis_angle" in t:
        aa = t.get("rotation_axis_angle", "vec4")
        rotation = np.array(axis_angle_quaternion(aa[:3], aa[3]))
    if not np.linalg.norm(rotation) > 0:
        raise FemError(f"{where}.rotation: quaternion must be non-zero")
    scale = t.get("scale", "float", 1.0)
    if not scale > 0:
        raise FemError(f"{where}.scale: must be > 0, got {scale}")
    placed = place_mesh(mesh, t.get("position", "vec3", (0, 0, 0)), rotation, scale)
    body = Body(name, placed, material, method)
    if t.get("fixed", "bool", False):
        body.pinned = np.arange(len(placed.vertices))
    if "pin" in t:
        sel = read_region(t.table("pin", REGION_KEYS[1:]), None, [body], f"{where}.pin", local_body=0)
        body.pinned = np.union1d(body.pinned, select_vertices(sel, [body], where)[0][1])
    return body


REGION_KEYS = ["body", "vertices", "sphere", "box"]


def read_region(t, body_name, bodies, where, local_body=None):
    """A Selection from the region keys of a table: body, vertices, sphere, box."""
    body = local_body
    name = t.get("body", "str", body_name)
    if name is not None and local_body is None:
        names = [b.name for b in bodies]
        if name not in names:
            hint = difflib.get_close_matches(name, names, n=1)
            also = f" (did you mean {hint[0]!r}?)" if hint else f"; bodies: {', '.join(names)}"
            raise FemError(f"{where}.body: no body named {name!r}{also}")
        body = names.index(name)
    sel = Selection(body)
    given = [k for k in ("vertices", "sphere", "box") if k in t]
    if len(given) > 1:
        raise FemError(f"{where}: give at most one of vertices, sphere, box (got {', '.join(given)})")
    if "vertices" in t:
        if body is None:
            raise FemError(f"{where}: a vertex list needs a body")
        sel.vertices = t.get("vertices", "ints")
        n = len(bodies[body].mesh.vertices)
        bad = sel.vertices[(sel.vertices < 0) | (sel.vertices >= n)]
        if len(bad):
            raise FemError(f"{where}.vertices: vertex {bad[0]} does not exist "
                           f"(body {bodies[body].name!r} has {n} vertices)")
    if "sphere" in t:
        s = t.table("sphere", ["center", "radius"])
        radius = s.require("radius", "float")
        if not radius > 0:
            raise FemError(f"{where}.sphere.radius: must be > 0, got {radius}")
        sel.sphere = (s.require("center", "vec3"), radius)
    if "box" in t:
        b = t.table("box", ["min", "max"])
        sel.box = (b.require("min", "vec3"), b.require("max", "vec3"))
    return sel


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


def read_initial(raw, where, bodies):
    kinds = ["velocity", "spin", "twist", "stretch", "squash", "twist_shape", "rotate"]
    t = Table(raw, where, REGION_KEYS + kinds)
    sel = read_region(t, None, bodies, where)
    given = [k for k in kinds if k in t]
    if len(given) != 1:
        raise FemError(f"{where}: give exactly one of {', '.join(kinds)}")
    kind = given[0]
    if kind == "velocity":
        return Initial(sel, kind, (t.get(kind, "vec3"),))
    spec = t.table(kind, ["axis", "omega", "factor", "angle_deg"])
    axis = spec.require("axis", "vec3")
    if not np.linalg.norm(axis) > 0:
        raise FemError(f"{where}.{kind}.axis: must be non-zero")
    axis = axis / np.linalg.norm(axis)
    if kind in ("spin", "twist"):
        return Initial(sel, kind, (axis, spec.require("omega", "float")))
    if kind in ("twist_shape", "rotate"):
        return Initial(sel, kind, (axis, np.radians(spec.require("angle_deg", "float"))))
    factor = spec.require("factor", "float")
    if not factor > 0:
        raise FemError(f"{where}.{kind}.factor: must be > 0, got {factor}")
    return Initial(sel, kind, (axis, factor))


def read_impulse(raw, where, bodies):
    t = Table(raw, where, REGION_KEYS + ["time", "delta_v"])
    time = t.get("time", "float", 0.0)
    if time < 0:
        raise FemError(f"{where}.time: must be >= 0, got {time}")
    return Impulse(time, read_region(t, None, bodies, where), t.require("delta_v", "vec3"))


def read_effects(t, path):
    e = Effects()
    if "gravity" in t:
        g = t.data["gravity"]
        if g is not False:
            e.gravity = tuple(check_type(g, "vec3", f"{path}: effects.gravity"))
    if "ground" in t:
        g = t.table("ground", ["height", "friction"])
        e.ground = g.get("height", "float", 0.0)
        e.friction = g.get("friction", "float", 0.5)
        if not 0 <= e.friction <= 1:
            raise FemError(f"{path}: effects.ground.friction must be in [0, 1], got {e.friction}")
    if "damping" in t:
        d = t.table("damping", ["alpha", "beta"])
        e.alpha, e.beta = d.get("alpha", "float", 0.0), d.get("beta", "float", 0.0)
        if e.alpha < 0 or e.beta < 0:
            raise FemError(f"{path}: effects.damping alpha and beta must be >= 0")
    return e


def read_solver(t):
    s = SolverSettings()
    s.dt = t.get("dt", "float", s.dt)
    s.step = t.get("step", "str", s.step)
    s.max_newton = t.get("max_newton", "int", s.max_newton)
    s.newton_tolerance = t.get("newton_tolerance", "float", s.newton_tolerance)
    s.method = t.get("method", "str", s.method)
    s.tolerance = t.get("tolerance", "float", s.tolerance)
    s.max_iterations = t.get("max_iterations", "int", s.max_iterations)
    s.jacobi_omega = t.get("jacobi_omega", "float", None)
    s.rotations = t.get("rotations", "str", s.rotations)
    return s
