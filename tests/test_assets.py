"""Tests for assets/: generators, surface tetrahedralisation and its cache, build_mesh."""

import functools
import os
from pathlib import Path

import numpy as np
import pytest

import assets
import assets.tetrahedralize as tetrahedralize
from assets.bunny import bunny, bunny_surface_path
from assets.generators import box, dome, statue
from fem.errors import FemError
from fem.mesh import OUTWARD_FACES, boundary_faces, mesh_quality, signed_volumes, write_tet_mesh

UNIT_TET = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]])


def surface_genus(mesh):
    """Check the mesh is a valid conforming FEM mesh and return its boundary's genus.

    Asserts: every tet positive, no face shared by more than two tets, every
    boundary edge shared by exactly two boundary faces (closed, manifold),
    and the volume the boundary encloses equals the tets' total volume.
    """
    volumes = signed_volumes(mesh.vertices, mesh.tets)
    assert (volumes > 0).all()
    all_faces = np.sort(mesh.tets[:, OUTWARD_FACES].reshape(-1, 3), axis=1)
    _, face_uses = np.unique(all_faces, axis=0, return_counts=True)
    assert face_uses.max() <= 2

    faces = boundary_faces(mesh.tets)
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique_edges, edge_uses = np.unique(edges, axis=0, return_counts=True)
    assert (edge_uses == 2).all()

    a, b, c = (mesh.vertices[faces[:, i]] for i in range(3))
    enclosed = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    assert enclosed == pytest.approx(volumes.sum(), rel=1e-9)

    euler = len(np.unique(faces)) - len(unique_edges) + len(faces)   # V - E + F = 2 - 2g
    assert euler % 2 == 0
    return (2 - euler) // 2


@pytest.mark.parametrize("split, min_angle", [(5, 54.7), (6, 45.0)])
def test_box(split, min_angle):
    mesh = box(size=(2.0, 1.0, 0.5), cells=(4, 3, 2), split=split)
    assert len(mesh.tets) == 4 * 3 * 2 * split
    assert len(mesh.vertices) == 5 * 4 * 3
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [-1.0, -0.5, -0.25])
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [1.0, 0.5, 0.25])
    assert signed_volumes(mesh.vertices, mesh.tets).sum() == pytest.approx(1.0, rel=1e-12)
    assert surface_genus(mesh) == 0
    assert len(boundary_faces(mesh.tets)) == 2 * 2 * (4 * 3 + 3 * 2 + 4 * 2)
    # Cubic cells would give 54.7 / 45 deg; these cells are stretched 2:1.
    assert mesh_quality(mesh)["min_dihedral_deg"] > 0.5 * min_angle


def test_dome_is_a_conforming_sphere_on_legs():
    mesh = dome()
    quality = mesh_quality(mesh)
    assert 2000 <= quality["tets"] <= 6000
    assert quality["min_dihedral_deg"] >= 10.0
    assert surface_genus(mesh) == 0
    low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    np.testing.assert_allclose(high, [1.0, 1.0, 1.0], atol=0.02)
    # Feet: leg_length below the sphere, whose surface is sqrt(3)/2 down at the legs.
    assert low[1] == pytest.approx(-np.sqrt(0.75) - 0.8, abs=0.05)
    # The 320-facet geodesic sphere holds 4.05 m^3; three legs add about 0.18.
    assert quality["volume"] == pytest.approx(4.05 + 0.18, rel=0.03)


def test_dome_resolution_scales_the_tet_count():
    coarse, fine = dome(resolution=8), dome(resolution=16)
    ratio = len(fine.tets) / len(coarse.tets)
    assert 5.0 < ratio < 11.0                        # about (16 / 8)^3
    assert surface_genus(coarse) == surface_genus(fine) == 0
    assert mesh_quality(coarse)["min_dihedral_deg"] >= 10.0


def test_dome_without_legs_is_a_ball():
    mesh = dome(legs=0, resolution=10)
    assert surface_genus(mesh) == 0
    assert mesh.vertices[:, 1].min() == pytest.approx(-1.0, abs=0.02)


def test_statue_has_holes():
    mesh = statue()
    quality = mesh_quality(mesh)
    assert 2000 <= quality["tets"] <= 3000
    assert quality["min_dihedral_deg"] >= 10.0
    assert surface_genus(mesh) == 3               # two arm loops and the gap between the legs
    height = np.ptp(mesh.vertices[:, 1])
    assert height == pytest.approx(1.5, abs=0.02)


def test_generators_are_deterministic():
    for make in (dome, statue):
        first, second = make(), make()
        np.testing.assert_array_equal(first.vertices, second.vertices)
        np.testing.assert_array_equal(first.tets, second.tets)


@pytest.mark.parametrize("make, message", [
    (lambda: box(cells=(0, 1, 1)), "cells must be >= 1"),
    (lambda: box(size=(1, float("nan"), 1)), "size must be three numbers"),
    (lambda: box(split=4), "split must be 5 or 6"),
    (lambda: dome(resolution=2), "resolution must be an integer >= 4"),
    (lambda: dome(leg_radius=2.0), "leg_radius must be in"),
    (lambda: statue(resolution=5), "resolution must be an integer >= 16"),
])
def test_generator_rejects_bad_parameters(make, message):
    with pytest.raises(FemError, match=message):
        make()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty FEM_CACHE_DIR, and a working directory to check for stray files."""
    monkeypatch.setenv("FEM_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    return tmp_path / "cache"


def test_tetrahedralised_sphere_keeps_its_volume_and_is_cached(tmp_path, cache, capfd):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    path = tmp_path / "sphere.obj"
    sphere.export(path)

    first = tetrahedralize.tetrahedralize_surface(path, edge_length=0.05)
    assert tetrahedralize.last_cache_hit is False
    out, err = capfd.readouterr()
    assert "tetrahedralising sphere.obj" in err and "done in" in err
    assert out == ""                               # wildmeshing's own chatter is kept out
    assert surface_genus(first) == 0
    assert signed_volumes(first.vertices, first.tets).sum() == pytest.approx(sphere.volume,
                                                                               rel=0.02)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "sphere.obj"]
    assert len(list(cache.glob("*.npz"))) == 1

    second = tetrahedralize.tetrahedralize_surface(path, edge_length=0.05)
    assert tetrahedralize.last_cache_hit is True
    assert capfd.readouterr().err == ""
    np.testing.assert_array_equal(second.vertices, first.vertices)
    np.testing.assert_array_equal(second.tets, first.tets)


def test_cache_key_depends_on_parameters_and_content(tmp_path, cache, monkeypatch):
    import trimesh

    runs = []

    def one_tet(vertices, faces, edge_length, path):
        """Stands in for wildmeshing: the tet spanned by the bounding box's axes."""
        runs.append(edge_length)
        corner, extent = vertices.min(axis=0), np.ptp(vertices, axis=0)
        tet_vertices = corner + np.vstack([np.zeros(3), np.diag(extent)])
        return tet_vertices, np.array([[0, 1, 2, 3]], dtype=np.int32)

    monkeypatch.setattr(tetrahedralize, "_run_wildmeshing", one_tet)
    path = tmp_path / "cube.stl"
    trimesh.creation.box(extents=(1.0, 2.0, 0.5)).export(path)
    for edge_length, hit in [(0.2, False), (0.2, True), (0.1, False), (0.1, True)]:
        mesh = tetrahedralize.tetrahedralize_surface(path, edge_length, progress=False)
        assert tetrahedralize.last_cache_hit is hit
    assert runs == [0.2, 0.1]
    assert signed_volumes(mesh.vertices, mesh.tets).sum() == pytest.approx(1.0 * 2.0 * 0.5 / 6)

    trimesh.creation.box(extents=(1.0, 2.0, 0.6)).export(path)
    tetrahedralize.tetrahedralize_surface(path, 0.2, progress=False)
    assert tetrahedralize.last_cache_hit is False
    assert len(list(cache.glob("*.npz"))) == 3


def truncated(entry):
    entry.write_bytes(entry.read_bytes()[:-40])


def fifo(entry):
    entry.unlink()
    os.mkfifo(entry)              # reading it would block forever


@pytest.mark.parametrize("damage", [lambda entry: entry.write_bytes(b"not a zip file"), truncated, fifo],
                         ids=["not a zip file", "truncated", "a FIFO"])
def test_damaged_cache_entry_is_rebuilt(tmp_path, cache, monkeypatch, damage):
    import trimesh

    monkeypatch.setattr(tetrahedralize, "_run_wildmeshing",
                        lambda vertices, faces, edge_length, path: (UNIT_TET, [[0, 1, 2, 3]]))
    path = tmp_path / "cube.obj"
    trimesh.creation.box().export(path)
    tetrahedralize.tetrahedralize_surface(path, progress=False)
    [entry] = cache.glob("*.npz")
    damage(entry)
    mesh = tetrahedralize.tetrahedralize_surface(path, progress=False)
    assert tetrahedralize.last_cache_hit is False
    assert len(mesh.tets) == 1
    assert entry.is_file()                         # rebuilt in place


def test_unreadable_surface_is_a_fem_error(tmp_path, cache):
    path = tmp_path / "broken.obj"
    path.write_text("this is not an OBJ file\n")
    with pytest.raises(FemError, match=r"broken\.obj"):
        tetrahedralize.tetrahedralize_surface(path)
    with pytest.raises(FemError, match=r"missing\.obj"):
        tetrahedralize.tetrahedralize_surface(tmp_path / "missing.obj")


@pytest.mark.slow
def test_bunny_from_pybullet(cache):
    import trimesh

    mesh = bunny()                                 # a cache miss: wildmeshing runs (~5 s)
    assert tetrahedralize.last_cache_hit is False
    quality = mesh_quality(mesh)
    assert 1000 <= quality["tets"] <= 10000
    assert quality["min_dihedral_deg"] > 1.0
    assert surface_genus(mesh) == 0
    diagonal = np.linalg.norm(np.ptp(mesh.vertices, axis=0))
    assert 1.0 <= diagonal <= 2.0
    surface_volume = trimesh.load(bunny_surface_path(), force="mesh").volume * 0.5**3
    assert quality["volume"] == pytest.approx(surface_volume, rel=0.02)

    again = bunny()
    assert tetrahedralize.last_cache_hit is True
    np.testing.assert_array_equal(again.tets, mesh.tets)


WHERE = "scenes/test.toml: body 'soft'.mesh"


def test_build_mesh_from_generator_file_and_surface(tmp_path, cache, monkeypatch):
    import trimesh

    from_generator = assets.build_mesh({"generator": "box", "cells": [2, 2, 2], "split": 6},
                                       tmp_path, WHERE)
    assert len(from_generator.tets) == 48

    (tmp_path / "meshes").mkdir()
    write_tet_mesh(from_generator, tmp_path / "meshes" / "cube.mesh")
    from_file = assets.build_mesh({"file": "meshes/cube.mesh"}, tmp_path, WHERE)
    np.testing.assert_array_equal(from_file.tets, from_generator.tets)

    runs = []

    def one_tet(vertices, faces, edge_length, path):
        runs.append((path.name, edge_length))
        return UNIT_TET, [[0, 1, 2, 3]]

    monkeypatch.setattr(tetrahedralize, "_run_wildmeshing", one_tet)
    trimesh.creation.box().export(tmp_path / "cube.obj")
    from_surface = assets.build_mesh({"surface": "cube.obj", "edge_length": 0.3}, tmp_path,
                                     WHERE)
    assert runs == [("cube.obj", 0.3)] and len(from_surface.tets) == 1
    assert set(assets.GENERATORS) == {"box", "dome", "statue", "bunny"}


@pytest.mark.parametrize("spec, message", [
    ({"generator": "dom"}, r"unknown generator 'dom' \(did you mean 'dome'\?\)"),
    ({"generator": "box", "sise": [1, 1, 1]}, r"unknown parameter 'sise' .*did you mean 'size'"),
    ({"generator": "box", "cells": [2, 2]}, r"cells must be a list of 3 numbers"),
    ({"generator": "box", "split": "5"}, r"split must be a number, got '5'"),
    ({"generator": "dome", "resolution": 8.5}, r"resolution must be an integer, got 8.5"),
    ({"generator": "box", "split": 7}, r"split must be 5 or 6"),
    ({"file": "missing.mesh"}, r"file 'missing.mesh' not found"),
    ({"file": "a.mesh", "scale": 2}, r"unknown parameter 'scale'"),
    ({"surface": "missing.obj"}, r"surface 'missing.obj' not found"),
    ({"generator": "box", "file": "a.mesh"}, r"needs exactly one of generator, file, surface"),
    ({"fiel": "a.mesh"}, r"did you mean 'file'"),
    ("box", r"must be a table"),
])
def test_build_mesh_errors_name_the_place(tmp_path, spec, message):
    with pytest.raises(FemError, match=message) as error:
        assets.build_mesh(spec, tmp_path, WHERE)
    assert str(error.value).startswith(WHERE)


def test_a_lattice_generators_mesh_is_cached_by_parameters_and_code(cache, monkeypatch):
    spec = {"generator": "dome", "resolution": 6}
    made = assets.build_mesh(spec, Path("."), "test")
    assert len(list(cache.glob("generated-*.npz"))) == 1

    @functools.wraps(dome)                # the same parameters
    def must_not_run(**params):
        raise AssertionError("built again instead of read from the cache")

    monkeypatch.setitem(assets.GENERATORS, "dome", must_not_run)
    again = assets.build_mesh(spec, Path("."), "test")
    np.testing.assert_array_equal(again.vertices, made.vertices)
    np.testing.assert_array_equal(again.tets, made.tets)
    assert again.source == made.source and again.tets.dtype == made.tets.dtype

    with pytest.raises(AssertionError, match="built again"):      # other parameters: another entry
        assets.build_mesh({"generator": "dome", "resolution": 7}, Path("."), "test")
    monkeypatch.setattr(assets, "GENERATOR_CODE", [Path(assets.__file__)])   # other code: another entry
    with pytest.raises(AssertionError, match="built again"):
        assets.build_mesh(spec, Path("."), "test")
