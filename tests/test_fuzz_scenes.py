"""Property-based fuzzing of scene descriptions by value (tests/test_fuzz.py mutates their text):
any value at any key of a TOML scene, and any `--set KEY=VALUE`, gives a Scene or a FemError,
never another exception; a scene that reads runs its first step. Derandomized.
"""

import copy
import tomllib

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fem
import scenes
from assets import build_mesh
from fem import mesh as fem_mesh
from fem.errors import FemError
from fem.scene_file import read_toml_scene
from cases import CUBE_MESH, TOML_SCENE

FUZZ = settings(max_examples=300, derandomize=True, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

BASE = tomllib.loads(TOML_SCENE)
BASE["body"].append({"name": "b", "mesh": {"generator": "box", "cells": [2, 2, 2]},
                     "material": {"E": 1e5, "nu": 0.3}, "position": [3.0, 0.0, 0.0]})

NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e308, -1e308, 1e-300, 5e-324, 1e15, 1e16, 1e13, 1e-8, 0.5, 0.4999999999, 100.0]),
    st.integers(-2**70, 2**70), st.sampled_from([0, 1, -1, 2**31, 2**31 - 1, 10**9]))
LEAVES = st.one_of(NUMBERS, st.booleans(), st.text(max_size=20),
                   st.sampled_from(["box", "dome", "statue", "bunny", "linear", "corotational", "pcg", "newton"]))
VALUES = st.recursive(LEAVES, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=3)),
                      max_leaves=12)
# Key paths of the base scene (and a few that are not in it), to put a value at.
PATHS = [("name",), ("solver", "dt"), ("solver", "tolerance"), ("solver", "max_iterations"), ("solver", "method"),
         ("solver", "step"), ("effects", "gravity"), ("effects", "ground"), ("effects", "damping", "alpha"),
         ("body", 0, "material", "E"), ("body", 0, "material", "nu"), ("body", 0, "material", "density"),
         ("body", 0, "position"), ("body", 0, "scale"), ("body", 0, "rotation"), ("body", 0, "pin"),
         ("body", 1, "mesh", "cells"), ("body", 1, "mesh", "size"), ("body", 1, "mesh", "generator"),
         ("body", 1, "mesh", "split"), ("body", 1, "mesh"), ("initial", 0, "velocity"), ("initial", 0, "vertices"),
         ("initial", 0, "spin"), ("impulse",), ("camera",), ("body",), ("body", 0, "method")]


@pytest.fixture(autouse=True)
def small_meshes(monkeypatch, tmp_path):
    """Fuzzed cell counts may ask for millions of tets: keep every mesh small and every cache here."""
    monkeypatch.setattr(fem_mesh, "MAX_TETS", 20_000)
    monkeypatch.setenv("FEM_CACHE_DIR", str(tmp_path / "cache"))


def put(data, path, value):
    """data with value at path, where the path still leads somewhere (an earlier change may
    have replaced a table on it)."""
    node = data
    for key in path[:-1]:
        if isinstance(node, list) and isinstance(key, int) and key < len(node):
            node = node[key]
        elif isinstance(node, dict) and isinstance(key, str):
            node = node.setdefault(key, {})
        else:
            return
    if isinstance(node, dict) or (isinstance(node, list) and path[-1] < len(node)):
        node[path[-1]] = value


def only_fem_errors(read):
    try:
        return read()
    except FemError as error:
        assert str(error)
        return None


@FUZZ
@given(changes=st.lists(st.tuples(st.sampled_from(PATHS), VALUES), min_size=1, max_size=3))
def test_any_value_at_any_key_gives_a_scene_or_a_fem_error(tmp_path, changes):
    (tmp_path / "cube.mesh").write_text(CUBE_MESH)
    data = copy.deepcopy(BASE)
    for path, value in changes:
        put(data, path, value)
    only_fem_errors(lambda: read_toml_scene(tmp_path / "s.toml", build_mesh, data))


SET_KEYS = st.one_of(st.sampled_from(["solver.dt", "solver.max_iterations", "body.0.material.E", "body.*.scale",
                                      "body.compliant.position", "body.0.mesh.cells", "body.1.mesh", "effects",
                                      "initial", "body.9.name", "x", "", ".", "body..x", "body.*"]),
                   st.text(max_size=30))
SET_VALUES = st.one_of(st.sampled_from(["1e308", "inf", "nan", "-1", "[1e300, 0, 0]", "[inf, 1, 1]", "{}", "[]",
                                        "[[[[[[]]]]]]", "true", '"x"', "{file = \"none.mesh\"}", "1e-300",
                                        "[" * 200 + "]" * 200, "{a = " * 50 + "1" + "}" * 50, "", "=", "[1,2"]),
                       st.text(max_size=40), NUMBERS.map(repr))


@FUZZ
@given(overrides=st.lists(st.tuples(SET_KEYS, SET_VALUES).map("=".join), min_size=1, max_size=3))
def test_any_set_value_gives_a_scene_or_a_fem_error(overrides):
    only_fem_errors(lambda: scenes.load_scene("cube", overrides=overrides))


@settings(max_examples=25, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(E=st.sampled_from([1e-300, 1.0, 1e13]), nu=st.sampled_from([-0.999, 0.0, 0.4999999]),
       density=st.sampled_from([1e-300, 1.0, 1e6]), dt=st.sampled_from([1e-8, 0.02, 100.0]),
       speed=st.sampled_from([0.0, 1e6, 1e15]))
def test_a_scene_at_the_edges_of_every_range_steps_without_an_exception(f64, E, nu, density, dt, speed):
    overrides = [f"body.*.material={{E={E!r}, nu={nu!r}, density={density!r}}}", f"solver.dt={dt!r}",
                 f"initial=[{{velocity=[{speed!r}, 0, 0]}}]"]
    scene = only_fem_errors(lambda: scenes.load_scene("cube", overrides=overrides))
    if scene is not None:
        info = fem.Simulation(scene).step()
        assert info["finite"] in (True, False)
