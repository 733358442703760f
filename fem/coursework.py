"""Reader for the coursework's `*-scene.txt` files (format in ../shared/cggs/README.md).

    <number of meshes>
    <mesh file> <density> <E> <nu> <isFixed 0|1> <cx cy cz> <qw qx qy qz>
    <number of impulses>
    <mesh index> <vertex index> <vx vy vz>        (sets that vertex's initial velocity)

Only as many impulse lines as the header promises are read, as the original
program did. The original program's settings apply: dt 0.02 s, Rayleigh
alpha = beta = 0.1, no gravity, no ground.
"""

from pathlib import Path

import numpy as np

from fem import limits
from fem.errors import FemError, excerpt, require_file
from fem.mesh import read_tet_mesh
from fem.scene import (Body, Effects, Initial, Material, Scene, Selection, SolverSettings, check_placed,
                       place_mesh)


def read_coursework_scene(path):
    path = Path(path)
    require_file(path, "scene file")
    limits.check_file_size(path, limits.MAX_SCENE_FILE_BYTES)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise FemError(f"{path}: cannot read: {e}") from None
    lines = [(n, line.split()) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
    cursor = iter(lines)

    def next_line(what, header=None):
        try:
            return next(cursor)
        except StopIteration:
            promised = f" (line {header} promises it)" if header else ""
            raise FemError(f"{path}: the file ends early, expected {what}{promised}") from None

    n, words = next_line("the number of meshes")
    n_meshes = parse_count(words, path, n, "number of meshes")
    limits.check_body_count(n_meshes, f"{path}:{n}")
    if n_meshes == 0:
        raise FemError(f"{path}:{n}: a scene needs at least one mesh, got 0")
    header = n
    bodies, meshes = [], {}
    for i in range(n_meshes):
        n, words = next_line(f"mesh line {i + 1} of {n_meshes}", header)
        if len(words) != 12:
            raise FemError(f"{path}:{n}: mesh line {i + 1} of {n_meshes} (promised on line {header}) "
                           f"needs 12 fields (file density E nu isFixed cx cy cz qw qx qy qz), "
                           f"got {len(words)}")
        density, E, nu, fixed, *pose = parse_numbers(words[1:], path, n)
        mesh_path = path.parent / words[0]
        if mesh_path not in meshes:
            try:
                meshes[mesh_path] = read_tet_mesh(mesh_path)
            except FemError as error:
                raise FemError(f"{path}:{n}: {error}") from None
        material = Material(E, nu, density)
        material.check(f"{path}:{n}")
        if fixed not in (0, 1):
            raise FemError(f"{path}:{n}: isFixed must be 0 or 1, got {fixed:g}")
        if not np.abs(pose[3:]).max() > 0:
            raise FemError(f"{path}:{n}: the rotation quaternion must be non-zero")
        placed = place_mesh(meshes[mesh_path], pose[:3], pose[3:])
        check_placed(placed.vertices, placed.tets, f"{path}:{n}")
        pinned = np.arange(len(placed.vertices)) if fixed else np.zeros(0, np.int64)
        bodies.append(Body(f"{Path(words[0]).stem}{i}", placed, material, "corotational", pinned))

    n, words = next_line("the number of impulses")
    n_impulses = parse_count(words, path, n, "number of impulses")
    header = n
    initial = []
    for i in range(n_impulses):
        n, words = next_line(f"impulse line {i + 1} of {n_impulses}", header)
        if len(words) != 5:
            raise FemError(f"{path}:{n}: impulse line {i + 1} of {n_impulses} (promised on line {header}) "
                           f"needs 5 fields (mesh vertex vx vy vz), got {len(words)}")
        body, vertex = (parse_index(w, path, n) for w in words[:2])
        velocity = np.array(parse_numbers(words[2:], path, n))
        if body >= len(bodies):
            raise FemError(f"{path}:{n}: impulse on mesh {body}, but the scene has {len(bodies)} meshes")
        n_vertices = len(bodies[body].mesh.vertices)
        if vertex >= n_vertices:
            raise FemError(f"{path}:{n}: impulse on vertex {vertex}, but mesh {body} has {n_vertices} vertices")
        initial.append(Initial(Selection(body, vertices=np.array([vertex])), "velocity", (velocity,)))

    return Scene(
        name=path.stem.removesuffix("-scene"),
        description=f"coursework scene {path.name}",
        path=str(path),
        bodies=bodies,
        effects=Effects(alpha=0.1, beta=0.1),
        solver=SolverSettings(dt=0.02),
        initial=initial,
    )


def parse_count(words, path, n, what):
    if len(words) != 1:
        raise FemError(f"{path}:{n}: expected the {what} alone on the line, got {excerpt(' '.join(words))}")
    return parse_index(words[0], path, n)


def parse_index(word, path, n):
    try:
        value = int(word)
    except ValueError:
        raise FemError(f"{path}:{n}: expected a non-negative integer, got {excerpt(word)}") from None
    if value < 0:
        raise FemError(f"{path}:{n}: expected a non-negative integer, got {value}")
    return value


def parse_numbers(words, path, n):
    try:
        values = [float(w) for w in words]
    except ValueError:
        bad = next(w for w in words if not is_float(w))
        raise FemError(f"{path}:{n}: expected a number, got {excerpt(bad)}") from None
    if not np.all(np.isfinite(values)):
        raise FemError(f"{path}:{n}: numbers must be finite, got {' '.join(words)}")
    return values


def is_float(word):
    try:
        float(word)
        return True
    except ValueError:
        return False
