"""Reading a Scene from a TOML file (the schema: `scenes/README.md`).

Every mistake is a FemError naming the file and the key, with the closest valid
key when a name is misspelt. Finding scenes by name and `--set` overrides live in
the `scenes` package; the meshes come from the `build_mesh` the caller passes.
"""

import difflib
import math
import tomllib
from pathlib import Path

import numpy as np

from fem import limits
from fem.errors import FemError, require_file
from fem.scene import (METHODS, Body, ContactEffect, Effects, Impulse, Initial, Material, Scene, Selection,
                       SolverSettings, axis_angle_quaternion, check_placed, place_mesh, select_vertices)


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
        if not abs(value) <= limits.MAX_MAGNITUDE:
            fail(f"a number no larger than {limits.MAX_MAGNITUDE:g}")
        return float(value)
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            fail("an integer")
        if not abs(value) <= limits.MAX_INTEGER:
            fail(f"an integer no larger than {limits.MAX_INTEGER}")
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


def read_toml_data(path):
    """The raw data (dict) of a TOML file."""
    path = Path(path)
    require_file(path, "scene file")
    limits.check_file_size(path, limits.MAX_SCENE_FILE_BYTES)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise FemError(f"{path}: not valid TOML: {e}") from None
    except RecursionError:
        raise FemError(f"{path}: tables or lists nested too deeply") from None
    except (OSError, UnicodeDecodeError) as e:
        raise FemError(f"{path}: cannot read: {e}") from None
    limits.check_nesting(data, path)
    return data


def read_toml_scene(path, build_mesh, data=None):
    """The Scene in a TOML file.

    build_mesh(spec, folder, where) -> TetMesh makes a body's mesh from its `mesh` table
    (the engine does not know where meshes come from: `assets.build_mesh` is the usual one).
    data: the scene's raw TOML data when it does not come from reading `path` (a
    mesh file's one-body scene, or a scene with overrides); `path` then names it in messages.
    """
    path = Path(path)
    if data is None:
        data = read_toml_data(path)
    top = Table(data, str(path), ["name", "description", "body", "effects", "solver",
                                  "initial", "impulse", "camera"])
    bodies_raw = data.get("body")
    if not isinstance(bodies_raw, list) or not bodies_raw:
        raise FemError(f"{path}: a scene needs at least one [[body]] table")
    limits.check_body_count(len(bodies_raw), path)
    bodies, tets = [], 0
    for i, raw in enumerate(bodies_raw):             # the total checked before the next mesh is made
        bodies.append(read_body(raw, i, path, build_mesh))
        tets += len(bodies[-1].mesh.tets)
        limits.check_scene_tets(tets, path)
    names = [b.name for b in bodies]
    if len(set(names)) != len(names):
        raise FemError(f"{path}: body names must be unique, got {names}")

    scene = Scene(
        name=top.get("name", "str", path.stem),
        description=top.get("description", "str", ""),
        path=str(path),
        bodies=bodies,
        effects=read_effects(top.table("effects", ["gravity", "ground", "contact", "damping", "stick_speed"]), path),
        solver=read_solver(top.table("solver", ["dt", "step", "integrator", "rho_infinity", "max_newton", "newton_tolerance", "method", "tolerance",
                                                 "max_iterations", "jacobi_omega", "preconditioner", "rotations", "sleep"])),
    )
    scene.solver.check(f"{path}: solver")
    for i, raw in enumerate(list_of_tables(data, "initial", path)):
        scene.initial.append(read_initial(raw, f"{path}: initial[{i}]", bodies))
    for i, raw in enumerate(list_of_tables(data, "impulse", path)):
        scene.impulses.append(read_impulse(raw, f"{path}: impulse[{i}]", bodies))
    if "camera" in data:
        cam = top.table("camera", ["eye", "target"])
        scene.camera = {"eye": cam.require("eye", "vec3"), "target": cam.require("target", "vec3")}
        if not np.linalg.norm(np.subtract(scene.camera["eye"], scene.camera["target"])) > 0:
            raise FemError(f"{path}: camera: eye and target are the same point; the camera looks nowhere")
    return scene


def list_of_tables(data, key, path):
    raw = data.get(key, [])
    if not isinstance(raw, list) or not all(isinstance(t, dict) for t in raw):
        raise FemError(f"{path}: {key} must be written as [[{key}]] tables")
    return raw


def read_body(raw, index, path, build_mesh):
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
    if not np.abs(rotation).max() > 0:          # not the norm: that of (1e-300, 0, 0, 0) underflows to 0
        raise FemError(f"{where}.rotation: quaternion must be non-zero")
    scale = t.get("scale", "float", 1.0)
    if not scale > 0:
        raise FemError(f"{where}.scale: must be > 0, got {scale}")
    placed = place_mesh(mesh, t.get("position", "vec3", (0, 0, 0)), rotation, scale)
    check_placed(placed.vertices, placed.tets, where)
    body = Body(name, placed, material, method)
    if t.get("fixed", "bool", False):
        body.pinned = np.arange(len(placed.vertices))
    if "pin" in t:
        sel = read_region(t.table("pin", REGION_KEYS[1:]), None, [body], f"{where}.pin", local_body=0)
        body.pinned = np.union1d(body.pinned, select_vertices(sel, [body], where)[0][1])
    return body


MAX_FRICTION = 10.0      # Coulomb's coefficient: rubber on rubber is about 1; above 10 it is a typo
MAX_STICK_SPEED = 1.0    # m/s: friction that holds below a walking pace is no longer friction

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
        if not 0 <= e.friction <= MAX_FRICTION:
            raise FemError(f"{path}: effects.ground.friction (Coulomb's coefficient) must be in "
                           f"[0, {MAX_FRICTION:g}], got {e.friction}")
    if "contact" in t:
        e.contact = read_contact(t.table("contact", ["distance", "friction"]), path)
    if "damping" in t:
        d = t.table("damping", ["alpha", "beta"])
        e.alpha, e.beta = d.get("alpha", "float", 0.0), d.get("beta", "float", 0.0)
        if e.alpha < 0 or e.beta < 0:
            raise FemError(f"{path}: effects.damping alpha and beta must be >= 0")
    e.stick_speed = t.get("stick_speed", "float", e.stick_speed)
    if not 0 < e.stick_speed <= MAX_STICK_SPEED:
        raise FemError(f"{path}: effects.stick_speed (m/s, below which friction holds) must be in "
                       f"(0, {MAX_STICK_SPEED:g}], got {e.stick_speed}")
    return e


def read_contact(t, path):
    """[effects] contact = { distance = d_hat (m, > 0), friction = mu }."""
    c = ContactEffect()
    c.distance = t.get("distance", "float", c.distance)
    c.friction = t.get("friction", "float", c.friction)
    if not (c.distance > 0 and math.isfinite(c.distance)):
        raise FemError(f"{path}: effects.contact.distance (the contact thickness, m) must be > 0, got {c.distance}")
    if not 0 <= c.friction <= MAX_FRICTION:
        raise FemError(f"{path}: effects.contact.friction (Coulomb's coefficient) must be in "
                       f"[0, {MAX_FRICTION:g}], got {c.friction}")
    return c


def read_solver(t):
    s = SolverSettings()
    s.dt = t.get("dt", "float", s.dt)
    s.step = t.get("step", "str", s.step)
    s.integrator = t.get("integrator", "str", s.integrator)
    s.rho_infinity = t.get("rho_infinity", "float", s.rho_infinity)
    s.max_newton = t.get("max_newton", "int", s.max_newton)
    s.newton_tolerance = t.get("newton_tolerance", "float", s.newton_tolerance)
    s.method = t.get("method", "str", s.method)
    s.tolerance = t.get("tolerance", "float", s.tolerance)
    s.max_iterations = t.get("max_iterations", "int", s.max_iterations)
    s.jacobi_omega = t.get("jacobi_omega", "float", None)
    s.preconditioner = t.get("preconditioner", "str", s.preconditioner)
    s.rotations = t.get("rotations", "str", s.rotations)
    s.sleep = t.get("sleep", "bool", s.sleep)
    return s
