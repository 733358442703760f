"""A user's own mesh file given where a scene is expected runs as a one-body scene.

Surfaces (OBJ, STL, PLY, OFF) are tetrahedralised and cached like the bunny; tet meshes
(.mesh, .msh, .vtk) are read as they are. Either way the body is scaled to 1 m across its
largest side and gets the documented defaults (assets.MESH_FILE_*).
"""

import contextlib
import io

import numpy as np
import pytest
import trimesh
from conftest import fan_tets

import assets
import fem
import scenes
import main
from assets import tetrahedralize
from fem.mesh import TetMesh, write_tet_mesh


def run(*argv):
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.redirect_stderr(err):
        code = main.main(list(argv))
    return code, out.getvalue(), err.getvalue()


@pytest.fixture
def here(tmp_path, monkeypatch):
    """An empty current folder and a cache of its own."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("FEM_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path


def ball(path, radius=30.0):
    """A closed icosphere surface (320 triangles) in millimetres-like units, written to path."""
    trimesh.creation.icosphere(subdivisions=2, radius=radius).export(path)
    return path


def largest_side(scene):
    x = scene.bodies[0].mesh.vertices
    return float((x.max(axis=0) - x.min(axis=0)).max())


def test_a_surface_runs_in_one_command_tetrahedralised_and_cached(here):
    ball(here / "ball.obj")
    code, out, err = run("simulate", "ball.obj", "--steps", "3")
    assert code == 0, err
    assert "tetrahedralising ball.obj" in err and "scene ball:" in out
    scene = scenes.load_scene("ball.obj")
    assert tetrahedralize.last_cache_hit                  # the second time comes from the cache
    assert len(scene.bodies) == 1 and scene.bodies[0].method == "corotational"
    assert largest_side(scene) == pytest.approx(assets.MESH_FILE_SIZE, rel=0.01)   # as its surface
    assert scene.bodies[0].material.E == assets.MESH_FILE_MATERIAL["E"]
    assert scene.effects.gravity is None and scene.effects.ground is None
    assert [i.kind for i in scene.initial] == ["twist_shape", "spin"]


@pytest.mark.parametrize("suffix", [".stl", ".ply", ".off"])
def test_every_surface_format_is_read(here, monkeypatch, suffix):
    monkeypatch.setattr(tetrahedralize, "_run_wildmeshing", fan_tets)   # instant: formats only
    scene = scenes.load_scene(ball(here / f"ball{suffix}"))
    assert scene.name == "ball" and len(scene.bodies[0].mesh.tets) > 100
    assert largest_side(scene) == pytest.approx(1.0, rel=1e-6)


@pytest.mark.parametrize("suffix", [".mesh", ".msh", ".vtk"])
def test_a_tet_mesh_file_runs_as_it_is(here, suffix):
    box = assets.box(size=(2.0, 1.0, 0.5), cells=(4, 2, 1))
    write_tet_mesh(TetMesh(box.vertices + 5.0, box.tets), here / f"part{suffix}")
    scene = scenes.load_scene(f"part{suffix}", overrides=["body.0.material.E=1e5"])
    body = scene.bodies[0]
    assert len(body.mesh.tets) == len(box.tets) and body.material.E == 1e5
    np.testing.assert_allclose(np.ptp(body.mesh.vertices, axis=0), [1.0, 0.5, 0.25])   # 2 m -> 1 m
    np.testing.assert_allclose(body.mesh.vertices.mean(axis=0), 0.0, atol=1e-12)


def test_a_missing_or_unknown_mesh_file_is_one_error_line(here):
    code, _, err = run("simulate", "nothere.stl")
    assert code == 2 and err == "error: nothere.stl: no such mesh file\n"
    (here / "notes.xyz").write_text("hello")
    code, _, err = run("simulate", "notes.xyz")
    assert code == 2 and err.startswith("error: notes.xyz: not a scene or mesh file (known: .toml")
