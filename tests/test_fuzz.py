"""Property-based fuzzing of the three readers: the only exception that may escape is FemError.

Inputs are valid files (tests/cases.py) mutated line by line or token by token, plus random
text. Derandomized, so CI sees the same examples every run.
"""

import string

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fem.coursework import read_coursework_scene
from fem.errors import FemError
from fem.mesh import read_tet_mesh
from assets import build_mesh
from fem.scene_file import read_toml_scene
from cases import COURSEWORK_SCENE, CUBE_MESH, TOML_SCENE

FUZZ = settings(max_examples=400, derandomize=True, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

GARBAGE = ["nan", "inf", "-inf", "-1", "0", "1e308", "-1e308", "1e-320", "99999999999", "2147483648",
           "-2147483649", "3.5", "x", "", "#", "[", "]", "{", "=", '"', "'", "\t", "Vertices", "End",
           "Tetrahedra", "Dimension", "true", "[1, 2]", "{a = 1}", "0x10", "1_000", "é"]


def token_mutation(text):
    """Strategy: `text` with some whitespace-separated tokens replaced by garbage or other tokens."""
    tokens = text.split(" ")

    @st.composite
    def mutate(draw):
        out = list(tokens)
        for _ in range(draw(st.integers(1, 4))):
            k = draw(st.integers(0, len(out) - 1))
            out[k] = draw(st.one_of(st.sampled_from(GARBAGE), st.sampled_from(tokens),
                                    st.floats(allow_nan=True, allow_infinity=True).map(repr),
                                    st.integers(-2**40, 2**40).map(str)))
        return " ".join(out)
    return mutate()


def line_mutation(text):
    """Strategy: `text` with lines deleted, duplicated, swapped or the file truncated."""
    lines = text.splitlines(keepends=True)

    @st.composite
    def mutate(draw):
        out = list(lines)
        for _ in range(draw(st.integers(1, 3))):
            if not out:
                break
            k = draw(st.integers(0, len(out) - 1))
            action = draw(st.sampled_from(["delete", "duplicate", "swap", "truncate"]))
            if action == "delete":
                del out[k]
            elif action == "duplicate":
                out.insert(k, out[k])
            elif action == "swap":
                j = draw(st.integers(0, len(out) - 1))
                out[k], out[j] = out[j], out[k]
            else:
                cut = "".join(out)[:draw(st.integers(0, len("".join(out))))]
                out = [cut]
        return "".join(out)
    return mutate()


def mutations(text):
    noise = st.text(alphabet=string.printable + "éΩ\x00", max_size=300)
    return st.one_of(token_mutation(text), line_mutation(text), noise,
                     st.tuples(token_mutation(text), line_mutation(text)).map(lambda p: p[1] + p[0]))


def only_fem_errors(read, path, *args):
    try:
        read(path, *args)
    except FemError as error:
        assert str(error)          # a message, never an empty error


@FUZZ
@given(text=mutations(CUBE_MESH))
def test_mesh_reader_raises_only_fem_errors(tmp_path, text):
    path = tmp_path / "cube.mesh"
    path.write_text(text)
    only_fem_errors(read_tet_mesh, path)


@FUZZ
@given(text=mutations(COURSEWORK_SCENE), mesh=st.one_of(st.just(CUBE_MESH), mutations(CUBE_MESH)))
def test_coursework_reader_raises_only_fem_errors(tmp_path, text, mesh):
    (tmp_path / "cube.mesh").write_text(mesh)
    path = tmp_path / "c-scene.txt"
    path.write_text(text)
    only_fem_errors(read_coursework_scene, path)


@FUZZ
@given(text=mutations(TOML_SCENE))
def test_toml_reader_raises_only_fem_errors(tmp_path, text):
    (tmp_path / "cube.mesh").write_text(CUBE_MESH)
    path = tmp_path / "s.toml"
    path.write_text(text)
    only_fem_errors(read_toml_scene, path, build_mesh)


@settings(max_examples=60, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=200))
def test_readers_survive_binary_files(tmp_path, data):
    (tmp_path / "cube.mesh").write_bytes(data)
    (tmp_path / "c-scene.txt").write_bytes(data)
    (tmp_path / "s.toml").write_bytes(data)
    only_fem_errors(read_tet_mesh, tmp_path / "cube.mesh")
    only_fem_errors(read_coursework_scene, tmp_path / "c-scene.txt")
    only_fem_errors(read_toml_scene, tmp_path / "s.toml", build_mesh)
