"""The built-in scenes (the TOML files in this folder) and how to find any scene.

`load_scene` takes a built-in name, a TOML path, a coursework `*-scene.txt` file or
a mesh file, applies `--set` overrides, and builds meshes with `assets.build_mesh`.
The engine (`fem`) reads the files; this package knows where they are.
"""

import copy
import os
import difflib
import tomllib
from pathlib import Path

from assets import MESH_FILE_SUFFIXES, build_mesh, mesh_file_scene
from fem.coursework import read_coursework_scene
from fem import limits
from fem.errors import FemError, excerpt, not_a_file, require_file
from fem.scene import ContactEffect
from fem.scene_file import read_toml_data, read_toml_scene

SCENES_DIR = Path(__file__).resolve().parent


def builtin_scenes():
    """{name: description} of every scene file shipped in scenes/."""
    out = {}
    for path in sorted(SCENES_DIR.glob("*.toml")):
        with open(path, "rb") as f:
            out[path.stem] = tomllib.load(f).get("description", "")
    return out


def load_scene(ref, overrides=None, contact=False):
    """A Scene from a built-in name, a .toml path, a coursework *-scene.txt path, or a mesh file.

    A mesh file (a surface: .obj .stl .ply .off, tetrahedralised and cached; or tets:
    .mesh .msh .vtk .vtu .node .ele) is a one-body scene with the defaults of
    `assets.mesh_file_scene`.
    overrides: ["key.path=value", ...] applied to a TOML scene before it is read,
    e.g. "solver.dt=0.01" or "body.soft.mesh.cells=[8, 8, 8]" (a body by name or index,
    or * for every body); paths in them are relative to the current folder.
    contact: switch on contact between bodies and within each (`[effects] contact`), with the
    scene's own settings where it has them, else the defaults (fem.scene.ContactEffect).
    """
    path = Path(ref)
    suffix = path.suffix.lower()
    if suffix == ".txt":
        if overrides:
            raise FemError(f"{path}: --set works on TOML scenes and mesh files only")
        scene = read_coursework_scene(path)
        if contact and scene.effects.contact is None:
            scene.effects.contact = ContactEffect()
        return scene
    if suffix in MESH_FILE_SUFFIXES:
        require_file(path, "mesh file")
        return read_with_overrides(path, with_contact(mesh_file_scene(path), contact), overrides or [])
    if suffix != ".toml":
        builtin = SCENES_DIR / f"{ref}.toml"
        if not builtin.exists():
            known = ", ".join([".toml", "-scene.txt", *MESH_FILE_SUFFIXES])
            if path.is_file():
                raise FemError(f"{path}: not a scene or mesh file (known: {known})")
            if os.path.lexists(path):
                raise FemError(f"{path}: {not_a_file(path)}; a scene is a built-in name or a file ({known})")
            names = list(builtin_scenes())
            hint = difflib.get_close_matches(str(ref), names, n=1)
            also = f" (did you mean {hint[0]!r}?)" if hint else f"; built-in scenes: {', '.join(names)}"
            raise FemError(f"{ref}: no such scene file or built-in scene{also}")
        path = builtin
    return read_with_overrides(path, with_contact(read_toml_data(path), contact), overrides or [])


def with_contact(data, contact):
    """Raw scene data with `[effects] contact` (an empty table: the defaults) where contact asks for it."""
    if contact and isinstance(data.get("effects", {}), dict):
        data.setdefault("effects", {}).setdefault("contact", {})
    return data


def read_with_overrides(path, data, overrides):
    """The Scene in raw TOML data with overrides applied. A mistake that only an
    override brings in is blamed on that override, not on the file."""
    def overridden(texts):
        changed = copy.deepcopy(data)
        for text in texts:
            apply_override(changed, text)
        return read_toml_scene(path, build_mesh, changed)

    try:
        return overridden(overrides)
    except FemError as error:
        if not overrides or str(error).startswith("--set "):   # apply_override already names it
            raise
        try:
            overridden([])
        except FemError:
            raise error from None                              # the file is wrong on its own
        for count in range(1, len(overrides) + 1):
            try:
                overridden(overrides[:count])
            except FemError as culprit:
                message = str(culprit).removeprefix(f"{path}: ")
                if message.startswith("--set "):
                    raise
                scene = f"built-in scene {path.stem}" if path.parent == SCENES_DIR else f"scene {path}"
                raise type(culprit)(f"--set {shortened(overrides[count - 1])}: {message} ({scene})") from None
        raise


def apply_override(data, text):
    """Set one "a.b.c=value" in the raw TOML data; value is TOML (a bare word counts as a string).

    A mesh path in it (a `file` or `surface` key) is relative to the current folder,
    where the user typed it, not to the scene file's folder.
    """
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise FemError(f"--set {excerpt(text)}: expected KEY=VALUE, e.g. solver.dt=0.01")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    except RecursionError:
        value = None
    if value is None or limits.nesting_depth(value) > limits.MAX_NESTING:
        raise FemError(f"--set {excerpt(text)}: tables or lists nested more than {limits.MAX_NESTING} deep")
    if key.count(".") > limits.MAX_NESTING:
        raise FemError(f"--set {excerpt(text)}: a key more than {limits.MAX_NESTING} levels deep")
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
                value[name] = user_path(value[name], key)
    elif parts[-1] in ("file", "surface") and isinstance(value, str) and value:
        value = user_path(value, key)
    node[parts[-1]] = value


def user_path(text, key):
    """The absolute path of a --set file name, with ~ or ~user expanded."""
    try:
        return str(Path(text).expanduser().absolute())
    except RuntimeError:                          # ~nouser: no such user
        raise FemError(f"--set {key}: {text}: no such user's home folder") from None


def shortened(text, limit=80):
    """A --set text as messages quote it: whole when short, else its start."""
    return text if len(text) <= limit else text[:limit] + "..."
