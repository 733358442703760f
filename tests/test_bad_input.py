"""Bad files and parameters (tests/cases.py BAD_INPUTS): one `error:` line naming the file, exit 2.

Most run `main.main` in this process (the error comes before Taichi compiles anything); a few
run `python main.py simulate` for real to check the exit code and that no traceback leaks.
"""

import subprocess
import sys

import numpy as np
import pytest

from cases import BAD_INPUTS, CUBE_MESH, ROOT, BadInput, run_bad_input

BY_NAME = {case.name: case for case in BAD_INPUTS}


@pytest.mark.parametrize("case", BAD_INPUTS, ids=[case.name for case in BAD_INPUTS])
def test_bad_input_gives_one_error_line(case, tmp_path):
    code, stderr = run_bad_input(case, tmp_path)
    lines = stderr.strip().splitlines()
    assert code == 2, stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    for words in case.expect:
        assert words in lines[0]


def simulate(case, folder, *extra):
    for name, text in case.files.items():
        (folder / name).write_text(text)
    return subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", *case.args, *extra],
                          cwd=folder, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("name", ["NaN coordinate", "coursework: header promises 3 impulses, has 2",
                                  "misspelt key", "--dt 0"])
def test_command_line_exits_2_without_traceback(name, tmp_path):
    run = simulate(BY_NAME[name], tmp_path)
    assert run.returncode == 2
    assert run.stderr.count("\n") == 1 and run.stderr.startswith("error: "), run.stderr
    assert run.stdout == ""


def test_debug_shows_the_traceback(tmp_path):
    run = simulate(BY_NAME["zero-volume tet"], tmp_path, "--debug")
    assert run.returncode != 0
    assert "Traceback" in run.stderr and "FemError" in run.stderr


def one_error_line(folder, *args):
    """The one `error:` line of `main.py simulate ARGS` run in `folder` (exit code 2 checked)."""
    code, stderr = run_bad_input(BadInput("", {}, list(args), []), folder)
    lines = stderr.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), stderr
    return lines[0]


def make(kind, path):
    """A thing at `path` that is not a readable file: a symbolic link loop, a folder, a dangling link."""
    if kind == "loop":
        path.symlink_to(path.name)
    elif kind == "folder":
        path.mkdir()
    else:
        path.symlink_to("gone.mesh")


@pytest.mark.parametrize("kind, says", [("loop", "a symbolic link that loops"), ("folder", "a folder, not a file"),
                                        ("dangling", "a symbolic link to 'gone.mesh', which does not exist")])
@pytest.mark.parametrize("name", ["m.mesh", "m.obj", "s.toml", "c-scene.txt"])
def test_a_path_that_is_no_file_is_named_for_what_it_is(tmp_path, kind, says, name):
    make(kind, tmp_path / name)
    line = one_error_line(tmp_path, name)
    assert name in line and says in line and "no such" not in line


def test_a_device_is_not_called_missing(tmp_path):
    line = one_error_line(tmp_path, "/dev/zero")
    assert "/dev/zero: a character device, not a file" in line


def test_a_file_name_with_a_newline_stays_on_one_line(tmp_path):
    (tmp_path / "new\nline.obj").write_text("not a surface\n")
    line = one_error_line(tmp_path, "new\nline.obj")
    assert "new\\nline.obj" in line


@pytest.mark.parametrize("suffix", [".vtu", ".msh", ".vtk"])
def test_a_mesh_with_a_hexahedron_beside_its_tets_is_refused(tmp_path, suffix):
    """5 tets and 1 hexahedron: running the tets alone would lose the hexahedron's volume."""
    import meshio

    hexahedron = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    points = np.vstack([hexahedron, hexahedron + [1, 0, 0]])
    tets = np.array([[8, 9, 11, 12], [9, 10, 11, 14], [9, 12, 13, 14], [11, 12, 14, 15], [9, 11, 12, 14]])
    mesh = meshio.Mesh(points, [("tetra", tets), ("hexahedron", [list(range(8))])])
    meshio.write(tmp_path / f"mixed{suffix}", mesh, **({"file_format": "gmsh22", "binary": False} if suffix == ".msh" else {}))
    line = one_error_line(tmp_path, f"mixed{suffix}")
    assert f"mixed{suffix}" in line and "1 hexahedron cell besides tetrahedra" in line


def test_a_medit_mesh_with_hexahedra_is_refused(tmp_path):
    text = (CUBE_MESH.replace("End", "Hexahedra\n1\n1 2 3 4 5 6 7 8 0\nEnd") if "End" in CUBE_MESH
            else CUBE_MESH + "\nHexahedra\n1\n1 2 3 4 5 6 7 8 0\n")
    (tmp_path / "cube.mesh").write_text(text)
    line = one_error_line(tmp_path, "cube.mesh")
    assert "cube.mesh:" in line and "1 hexahedron cell besides tetrahedra" in line


@pytest.mark.parametrize("kind, says", [("loop", "a symbolic link that loops"), ("folder", "a folder, not a file")])
def test_a_scene_whose_mesh_is_no_file_says_what_it_is(tmp_path, kind, says):
    make(kind, tmp_path / "m.mesh")
    (tmp_path / "s.toml").write_text('[[body]]\nname = "b"\nmesh = { file = "m.mesh" }\n')
    line = one_error_line(tmp_path, "s.toml")
    assert "s.toml" in line and "m.mesh" in line and says in line
