"""What the program trusts (issue 24, "trust" and a new user's trips): the mesh cache, Taichi's
environment variables, surfaces that are not closed or not surfaces, abbreviated options."""

import os
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from assets import build_mesh, cache_dir
from assets.tetrahedralize import cached_mesh, load_surface, write_cache_entry
from fem.errors import FemError
from fem.mesh import signed_volumes
from test_cli import ROOT, here, one_error_line, run  # noqa: F401  (here is a fixture)

DOME = {"generator": "dome", "resolution": 6, "legs": 2}


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FEM_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def poison(entry, checksum_matches):
    """Rewrite a cache entry with a vertex index of -1408, as a hostile user could."""
    with np.load(entry) as data:
        arrays = {name: data[name] for name in data.files}
    arrays["tets"][7, 2] = -1408
    if checksum_matches:
        write_cache_entry(entry, (arrays["vertices"], arrays["tets"]), source=arrays["source"])
    else:
        np.savez(entry, **arrays)


@pytest.mark.parametrize("checksum_matches", [False, True], ids=["altered", "altered with a new checksum"])
def test_a_poisoned_cache_entry_is_rebuilt_not_run(cache, checksum_matches):
    first = build_mesh(DOME, ".", "test")
    [entry] = cache_dir().glob("generated-*.npz")
    poison(entry, checksum_matches)
    again = build_mesh(DOME, ".", "test")
    assert again.tets.min() >= 0 and (signed_volumes(again.vertices, again.tets) > 0).all()
    np.testing.assert_array_equal(again.tets, first.tets)
    assert cached_mesh(entry, "test", "source") is not None          # and the entry is whole again


def test_a_cache_entry_is_checked_like_a_mesh_file(cache):
    cache.mkdir()
    vertices = np.eye(4, 3)
    write_cache_entry(cache / "x.npz", (vertices, np.array([[0, 1, 2, 3], [0, 1, 2, 9]])))
    assert cached_mesh(cache / "x.npz", "x") is None


def start(env, *argv):
    return subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", "cube", "--steps", "1", *argv],
                          capture_output=True, text=True, timeout=300, env={**os.environ, **env})


@pytest.mark.parametrize("value", ["opengl", "xyz"])
def test_the_command_line_wins_over_ti_arch(value):
    result = start({"TI_ARCH": value}, "--arch", "cpu")
    assert result.returncode == 0, result.stderr
    assert f"TI_ARCH='{value}' ignored" in result.stderr and "x64" in result.stdout


def test_a_taichi_variable_it_cannot_use_is_one_error_line():
    result = start({"TI_CPU_MAX_NUM_THREADS": "abc"})
    assert result.returncode == 2
    one_error_line(result.stderr, "TI_CPU_MAX_NUM_THREADS", "unset it")


def surfaces(folder):
    open_sphere = trimesh.creation.icosphere(2)
    open_sphere.faces = open_sphere.faces[1:]
    open_sphere.export(folder / "open.obj")
    open_box = trimesh.creation.box()
    open_box.faces = open_box.faces[2:]                 # no top
    open_box.export(folder / "lidless.stl")
    (folder / "triangle.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (folder / "nan.obj").write_text("v nan 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
    rng = np.random.default_rng(24)
    for name in ("random.stl", "random.obj", "random.ply", "random.off"):
        (folder / name).write_bytes(rng.bytes(600))


@pytest.mark.parametrize("name", ["open.obj", "lidless.stl", "triangle.obj"])
def test_a_surface_that_is_not_closed_is_refused_naming_its_open_edges(tmp_path, name):
    surfaces(tmp_path)
    with pytest.raises(FemError, match=r"not closed: \d+ edges have a triangle on one side only"):
        load_surface(tmp_path / name)


@pytest.mark.parametrize("name", ["nan.obj", "random.stl", "random.obj", "random.ply", "random.off"])
def test_a_surface_that_is_not_one_is_one_error_line_and_caches_nothing(here, cache, name):
    surfaces(here)
    code, out, err = run("simulate", name, "--steps", "1")
    assert code == 2
    line = one_error_line(err, name)
    assert "ModuleNotFoundError" not in line
    assert not cache.exists() or not list(cache.iterdir())


def test_an_obj_vertex_without_three_coordinates_is_named_by_its_line(tmp_path):
    """trimesh's own error for it is numpy's ("operands could not be broadcast together")."""
    (tmp_path / "short.obj").write_text("# a tetrahedron\nv 0 0 0\nv 1 0\nv 0 1 0\nv 0 0 1\n"
                                        "f 1 2 3\nf 1 3 4\nf 1 4 2\nf 2 4 3\n")
    (tmp_path / "word.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 one 0\nv 0 0 1\nf 1 2 3\n")
    for name, line in (("short.obj", "line 3: a vertex needs x y z, got 'v 1 0'"),
                       ("word.obj", "line 3: a vertex needs x y z, got 'v 0 one 0'")):
        try:
            load_surface(tmp_path / name)
        except FemError as error:
            assert line in str(error), error
        else:    # a reader that pads or skips the line must still not hand back a surface from it
            raise AssertionError(f"{name} was read")


@pytest.mark.parametrize("argv", [["export", "cube86", "--steps", "5"], ["simulate", "cube86", "--stat", "x"],
                                  ["simulate", "cube86", "--over"]])
def test_abbreviated_options_are_refused(here, argv):
    code, out, err = run(*argv)
    assert code == 2
    one_error_line(err, "unrecognized arguments")


def test_the_hint_for_options_without_a_command_names_a_command_that_takes_them(here):
    code, out, err = run("--steps", "5")
    assert code == 2
    one_error_line(err, "main.py simulate epcot --steps 5")
    code, out, err = run("--frames", "5")
    one_error_line(err, "main.py export epcot --frames 5")


def test_compare_labels_follow_the_methods_and_the_panel_names_them():
    from types import SimpleNamespace

    from app.window.panel import shown_name
    from app.window.viewer import copy_methods
    assert copy_methods(["linear", "corotational"], 1) == ["linear", "corotational"]
    assert copy_methods(["linear", "linear", "linear", "linear"], 2) == ["linear", "linear"]
    assert copy_methods(["linear", "corotational", "corotational", "corotational"], 2) == ["mixed", "corotational"]
    body = SimpleNamespace(name="cube (linear)", method="corotational")
    assert shown_name(body, 1) == "cube (corotational)" and shown_name(body, 0) == "cube (linear)"


def test_a_drag_arrow_starts_at_the_hit_point_and_points_to_the_mouse():
    from app.window.viewer import arrow_beads
    point, push = np.zeros(3), np.array([2.0, 0.0, 0.0])
    drag = arrow_beads(point, push, 0.5, 5, "tail")
    np.testing.assert_allclose(drag[[0, -1]], [[0, 0, 0], [1, 0, 0]])
    click = arrow_beads(point, push, 0.5, 5, "tip")
    np.testing.assert_allclose(click[[0, -1]], [[-1, 0, 0], [0, 0, 0]])


def test_an_installed_package_says_how_to_get_the_benchmark_figure(tmp_path, monkeypatch):
    from app.bench import report
    from app.commands import figures
    monkeypatch.setattr(report, "DOCS", tmp_path / "site-packages" / "docs")       # not there once installed
    maker = figures.Maker(quick=True, cggs=None, bench_results=report.DOCS / "benchmark.json")
    why = figures.benchmark_missing(maker)
    assert "installed package has no docs/" in why and "bench --out DIR" in why and "--docs" not in why
