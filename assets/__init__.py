"""Where meshes come from: procedural generators, tet mesh files, surfaces.

`build_mesh` turns the `mesh` table of a scene file into a `TetMesh`:

    {generator = "box", size = [1, 1, 1], cells = [4, 4, 4]}   # see GENERATORS
    {file = "meshes/part.mesh"}                                # a tet mesh file
    {surface = "shapes/cup.obj", edge_length = 0.05}           # tetrahedralised, cached

`mesh_file_scene` makes a one-body scene of a mesh file, so that a user's own
shape runs with `main.py simulate my_shape.obj`.
"""

import difflib
import math
import hashlib
import inspect
from pathlib import Path

import numpy as np

from fem.errors import FemError, excerpt, not_a_file
from fem.limits import MAX_INTEGER
from fem.mesh import MESHIO_READ_EXTENSIONS, TetMesh, read_tet_mesh

from assets.bunny import bunny
from assets.generators import box, dome, statue
from assets.tetrahedralize import (cache_dir, cached_mesh, load_surface, tetrahedralize_surface,
                                   write_cache_entry)

GENERATORS = {"box": box, "dome": dome, "statue": statue, "bunny": bunny}
# Generators that take a noticeable part of a start (a few tenths of a second): their meshes
# are cached beside the tetrahedralised surfaces, keyed by the parameters and the code.
CACHED_GENERATORS = {"dome", "statue"}
GENERATOR_CODE = [Path(__file__).parent / name for name in ("generators.py", "lattice.py")]

SOURCES = ("generator", "file", "surface")

SURFACE_SUFFIXES = (".obj", ".stl", ".ply", ".off")
TET_MESH_SUFFIXES = (".mesh", *MESHIO_READ_EXTENSIONS)
MESH_FILE_SUFFIXES = SURFACE_SUFFIXES + TET_MESH_SUFFIXES

# A mesh file run as a scene (documented in scenes/README.md): the body is scaled to
# MESH_FILE_SIZE metres across its largest side, whatever the file's units, so that the
# material, the time step and the window's push suit it; then, as in the epcot scene,
# wrung about the vertical and set spinning, where linear FEM visibly flattens and grows.
MESH_FILE_SIZE = 1.0            # m
MESH_FILE_EDGE_LENGTH = 0.05    # of a surface's bounding-box diagonal: a few thousand tets
MESH_FILE_MATERIAL = {"E": 5e4, "nu": 0.4, "density": 1000.0}


def mesh_file_scene(path):
    """The raw TOML data of a one-body scene made of the mesh file at `path` (a surface
    .obj/.stl/.ply/.off, tetrahedralised and cached, or a tet mesh), with the defaults above;
    scenes.load_scene reads it like a scene file, so --set changes any of it."""
    path = Path(path).absolute()
    if path.suffix.lower() in SURFACE_SUFFIXES:
        mesh = {"surface": str(path), "edge_length": MESH_FILE_EDGE_LENGTH}
        vertices = load_surface(path)[0]     # the tets fill the surface: the same size
    else:
        mesh = {"file": str(path)}
        vertices = read_tet_mesh(path).vertices
    largest_side = float((vertices.max(axis=0) - vertices.min(axis=0)).max())
    if not largest_side > 0:
        raise FemError(f"{path}: every vertex is at the same point; a shape needs a size")
    return {
        "name": path.stem,
        "description": f"{path.name}: wrung and spun, no gravity (the defaults for a mesh file)",
        "solver": {"dt": 0.02, "tolerance": 1e-3, "max_iterations": 200},
        "effects": {"damping": {"alpha": 0.1, "beta": 0.02}},
        "body": [{"name": path.stem, "mesh": mesh, "material": dict(MESH_FILE_MATERIAL),
                  "scale": MESH_FILE_SIZE / largest_side}],
        "initial": [{"twist_shape": {"axis": [0.0, 1.0, 0.0], "angle_deg": 60.0}},
                    {"spin": {"axis": [1.0, 0.3, 0.0], "omega": 0.5}}],
    }


def build_mesh(spec, base_dir, where):
    """The `TetMesh` a scene's mesh table describes.

    spec: the table (a dict) with exactly one of "generator", "file" or
    "surface". base_dir: the folder relative paths start from (the scene
    file's folder). where: the prefix for error messages, e.g.
    "scenes/cube.toml: body 'soft'.mesh".
    """
    if not isinstance(spec, dict):
        raise FemError(f"{where} must be a table, got {spec!r}")
    given = [key for key in SOURCES if key in spec]
    if len(given) != 1:
        hint = _closest_hint(next(iter(spec), ""), SOURCES) if not given else ""
        raise FemError(f"{where} needs exactly one of {', '.join(SOURCES)}, "
                       f"got {', '.join(map(repr, spec)) or 'none'}{hint}")
    try:
        if given == ["generator"]:
            return _from_generator(spec)
        if given == ["file"]:
            _check_keys(spec, {"file"}, "a file mesh")
            return read_tet_mesh(_existing_path(spec["file"], base_dir, "file"))
        _check_keys(spec, {"surface", "edge_length"}, "a surface mesh")
        edge_length = _typed(spec.get("edge_length", 0.05), 0.05, "edge_length")
        return tetrahedralize_surface(_existing_path(spec["surface"], base_dir, "surface"),
                                      edge_length)
    except FemError as error:   # the same kind of error, saying which mesh table it is
        raise type(error)(f"{where}: {error}") from None


def _from_generator(spec):
    name = spec["generator"]
    if not isinstance(name, str) or name not in GENERATORS:
        raise FemError(f"unknown generator {name!r}{_closest_hint(str(name), GENERATORS)}; "
                       f"known: {', '.join(GENERATORS)}")
    generator = GENERATORS[name]
    defaults = {parameter.name: parameter.default
                for parameter in inspect.signature(generator).parameters.values()}
    _check_keys(spec, {"generator", *defaults}, f"generator {name!r}")
    params = {key: _typed(value, defaults[key], key)
              for key, value in spec.items() if key != "generator"}
    if name not in CACHED_GENERATORS:
        return generator(**params)
    key = hashlib.sha256(f"{name}|{sorted(params.items())!r}".encode())
    for path in GENERATOR_CODE:
        key.update(path.read_bytes())
    cached = cache_dir() / f"generated-{key.hexdigest()}.npz"
    entry = cached_mesh(cached, "cache", "source")
    if entry is not None:
        mesh, source = entry
        return TetMesh(mesh.vertices, mesh.tets, str(source))
    mesh = generator(**params)
    write_cache_entry(cached, (mesh.vertices, mesh.tets), source=np.array(mesh.source))
    return mesh


def _check_keys(spec, allowed, what):
    for key in spec:
        if key not in allowed:
            raise FemError(f"unknown parameter {key!r} for {what}"
                           f"{_closest_hint(key, allowed)}; valid: {', '.join(sorted(allowed - {'generator'}))}")


def _closest_hint(word, choices):
    close = difflib.get_close_matches(word, list(choices), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _typed(value, default, key):
    """`value` converted to the type of the parameter's default, or FemError.

    Numbers: an int default wants an integer, a float default any number.
    Tuples: the same number of entries, each checked against its default.
    """
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or len(value) != len(default):
            raise FemError(f"{key} must be a list of {len(default)} numbers, got {value!r}")
        return tuple(_typed(v, d, f"{key}[{i}]") for i, (v, d) in enumerate(zip(value, default)))
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise FemError(f"{key} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise FemError(f"{key} must be a finite number, got {value!r}")
    if isinstance(default, int):
        if not float(value).is_integer():
            raise FemError(f"{key} must be an integer, got {value!r}")
        if abs(value) > MAX_INTEGER:        # cells = [1e200, 1, 1]: a count with 200 digits
            raise FemError(f"{key} must be an integer between -{MAX_INTEGER:,} and {MAX_INTEGER:,} (the "
                           f"engine counts in 32-bit integers), got {value!r}")
        return int(value)
    return float(value)


def _existing_path(value, base_dir, key):
    if not isinstance(value, str) or not value:
        raise FemError(f"{key} must be a path string, got {value!r}")
    path = Path(value)
    if not path.is_absolute():
        path = Path(base_dir) / path
    reason = not_a_file(path)
    if reason == "no such file":
        raise FemError(f"{key} {value!r} not found (looked for {path})")
    if reason is not None:
        raise FemError(f"{key} {excerpt(value, 80)}: {reason}")
    return path
