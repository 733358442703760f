"""Tests for fem/mesh.py: checks, orientation, boundary, and file I/O."""

import re
from pathlib import Path

import numpy as np
import pytest

from fem.errors import FemError
from fem.mesh import (TetMesh, boundary_faces, mesh_quality, prepare_mesh, read_tet_mesh,
                      signed_volumes, write_tet_mesh)

CGGS = Path(__file__).resolve().parents[2] / "shared" / "cggs"

UNIT_TET = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]])

# A unit cube split into 5 tets (4 corners + 1 regular tet in the middle), 1-based
# indices and a ref column, with a Triangles section the reader must skip.
CUBE_MEDIT = """MeshVersionFormatted 1
Dimension
3
Vertices
8
0 0 0 1
1 0 0 1
0 1 0 1
1 1 0 1
0 0 1 1
1 0 1 1
0 1 1 1
1 1 1 1
Triangles
2
1 2 3 0
2 3 4 0
TETRAHEDRA
5
1 2 3 5 0
4 2 3 8 0
6 2 5 8 0
7 3 5 8 0
2 3 5 8 0
End
"""


def write(tmp_path, text, name="shape.mesh"):
    path = tmp_path / name
    path.write_text(text)
    return path


def edges_of(faces):
    """Undirected edges of triangles with how many triangles use each."""
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    return np.unique(edges, axis=0, return_counts=True)


def enclosed_volume(vertices, faces):
    """Volume inside a closed outward-oriented triangle surface (divergence theorem)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0


def test_medit_one_based_cube(tmp_path):
    mesh = read_tet_mesh(write(tmp_path, CUBE_MEDIT))
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.shape == (8, 3)
    assert mesh.tets.dtype == np.int32 and mesh.tets.shape == (5, 4)
    assert mesh.tets.min() == 0 and mesh.tets.max() == 7
    volumes = signed_volumes(mesh.vertices, mesh.tets)
    assert (volumes > 0).all()
    assert volumes.sum() == pytest.approx(1.0, abs=1e-12)
    assert volumes[4] == pytest.approx(1 / 3)


def test_medit_zero_based_matches_one_based(tmp_path):
    one_based = read_tet_mesh(write(tmp_path, CUBE_MEDIT, "one.mesh"))
    lines = CUBE_MEDIT.splitlines()
    start = lines.index("TETRAHEDRA") + 2
    for k in range(start, start + 5):
        *indices, ref = lines[k].split()
        lines[k] = " ".join(str(int(i) - 1) for i in indices) + " " + ref
    zero_based = read_tet_mesh(write(tmp_path, "\n".join(lines), "zero.mesh"))
    np.testing.assert_array_equal(zero_based.tets, one_based.tets)


def test_negative_tet_is_reoriented():
    mesh = prepare_mesh(UNIT_TET, [[1, 0, 2, 3]], "test")
    assert signed_volumes(UNIT_TET, [[1, 0, 2, 3]])[0] == pytest.approx(-1 / 6)
    assert signed_volumes(mesh.vertices, mesh.tets)[0] == pytest.approx(1 / 6)
    assert sorted(mesh.tets[0]) == [0, 1, 2, 3]


def test_zero_volume_tet_is_rejected_by_index():
    vertices = np.vstack([UNIT_TET, [[0.5, 0.5, 0.0]]])   # vertex 4 lies in the z=0 plane
    with pytest.raises(FemError, match=r"flat\.mesh: tet 1 .*near-zero volume"):
        prepare_mesh(vertices, [[0, 1, 2, 3], [0, 1, 3, 4]], "flat.mesh")


def test_repeated_vertex_is_rejected():
    with pytest.raises(FemError, match="tet 0 repeats a vertex"):
        prepare_mesh(UNIT_TET, [[0, 1, 1, 3]], "test")


def test_single_tet_boundary_is_four_outward_faces():
    faces = boundary_faces(np.array([[0, 1, 2, 3]]))
    assert faces.shape == (4, 3) and faces.dtype == np.int32
    centroid = UNIT_TET.mean(axis=0)
    for face in faces:
        a, b, c = UNIT_TET[face]
        normal = np.cross(b - a, c - a)
        assert normal @ ((a + b + c) / 3 - centroid) > 0


def test_box_boundary_is_closed_manifold_and_encloses_the_tet_volume(tmp_path):
    # A 2x1x1 box: the cube plus its mirror image about the plane x = 1, so the
    # two cubes split their shared face along the same diagonal.
    cube = read_tet_mesh(write(tmp_path, CUBE_MEDIT))
    far_corners = [0, 2, 4, 6]                          # the cube's x = 0 vertices
    mirrored = cube.vertices[far_corners] * [-1, 1, 1] + [2, 0, 0]
    vertices = np.vstack([cube.vertices, mirrored])
    mirror_index = np.arange(8)
    mirror_index[far_corners] = [8, 9, 10, 11]
    tets = np.vstack([cube.tets, mirror_index[cube.tets]])
    mesh = prepare_mesh(vertices, tets, "two cubes")

    faces = boundary_faces(mesh.tets)
    assert len(faces) == 2 * 5 * 2           # 10 unit squares, 2 triangles each
    _, uses = edges_of(faces)
    assert (uses == 2).all()
    tet_volume = signed_volumes(mesh.vertices, mesh.tets).sum()
    assert tet_volume == pytest.approx(2.0)
    assert enclosed_volume(mesh.vertices, faces) == pytest.approx(tet_volume, rel=1e-12)


def test_mesh_quality_of_the_cube(tmp_path):
    quality = mesh_quality(read_tet_mesh(write(tmp_path, CUBE_MEDIT)))
    assert quality["tets"] == 5 and quality["vertices"] == 8
    assert quality["boundary_faces"] == 12
    assert quality["volume"] == pytest.approx(1.0)
    # Corner tets have right angles and arccos(1/sqrt(3)) = 54.7 deg edges.
    assert quality["min_dihedral_deg"] == pytest.approx(np.degrees(np.arccos(1 / np.sqrt(3))))


@pytest.mark.parametrize("extension", [".mesh", ".msh", ".vtu", ".vtk"])
def test_write_read_round_trip_is_exact(tmp_path, extension):
    rng = np.random.default_rng(0)
    cube = read_tet_mesh(write(tmp_path, CUBE_MEDIT))
    mesh = TetMesh(cube.vertices + rng.normal(scale=0.01, size=(8, 3)), cube.tets)
    path = tmp_path / f"out{extension}"
    write_tet_mesh(mesh, path)
    back = read_tet_mesh(path)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_write_unknown_extension_is_an_error(tmp_path):
    mesh = prepare_mesh(UNIT_TET, [[0, 1, 2, 3]], "test")
    with pytest.raises(FemError, match=r"out\.obj: cannot write"):
        write_tet_mesh(mesh, tmp_path / "out.obj")


def replace_line(text, number, new):
    lines = text.splitlines()
    lines[number - 1] = new
    return "\n".join(lines) + "\n"


BAD_FILES = {
    "empty": ("", r"bad\.mesh: the file is empty"),
    "truncated": (CUBE_MEDIT[:CUBE_MEDIT.index("4 2 3 8")],
                  r"bad\.mesh:18: TETRAHEDRA says 5 tets but the file ends after 1"),
    "vertex count too large": (replace_line(CUBE_MEDIT, 5, "9"),
                               r"bad\.mesh:14: Vertices says 9 vertices but 'Triangles'"),
    "vertex count too small": (replace_line(CUBE_MEDIT, 5, "7"),
                               r"bad\.mesh:13: expected a keyword"),
    "index out of range": (replace_line(CUBE_MEDIT, 20, "1 2 3 9 0"),
                           r"bad\.mesh:20: tet 0 refers to vertex 9, but the file has 8"),
    "NaN coordinate": (replace_line(CUBE_MEDIT, 8, "1 1 nan 1"),
                       r"bad\.mesh:8: vertex 2 has a non-finite coordinate"),
    "inf coordinate": (replace_line(CUBE_MEDIT, 8, "1 1 -inf 1"),
                       r"bad\.mesh:8: vertex 2 has a non-finite coordinate"),
    "non-numeric coordinate": (replace_line(CUBE_MEDIT, 7, "1 zero 0 1"),
                               r"bad\.mesh:7: vertex 1 has a non-numeric coordinate 'zero'"),
    "non-integer index": (replace_line(CUBE_MEDIT, 21, "4 2 3.5 8 0"),
                          r"bad\.mesh:21: tet 1 has a vertex index '3.5'"),
    "short vertex row": (replace_line(CUBE_MEDIT, 6, "0 0"),
                         r"bad\.mesh:6: vertex 0 has 2 value\(s\), expected 3"),
    "zero-volume tet": (replace_line(CUBE_MEDIT, 22, "1 2 3 4 0"),
                        r"bad\.mesh:22: tet 2 .*near-zero volume"),
    "no tets": (CUBE_MEDIT[:CUBE_MEDIT.index("TETRAHEDRA")], r"bad\.mesh: no tetrahedra"),
    "2-D": (replace_line(CUBE_MEDIT, 3, "2"), r"bad\.mesh:2: only 3-D meshes"),
    "bad count": (replace_line(CUBE_MEDIT, 5, "eight"),
                  r"bad\.mesh:5: Vertices count must be a non-negative integer"),
    "binary junk": ("\x00\xff\xfe", r"bad\.mesh"),
}


@pytest.mark.parametrize("case", BAD_FILES)
def test_bad_medit_file_names_file_and_line(tmp_path, case):
    text, message = BAD_FILES[case]
    path = tmp_path / "bad.mesh"
    path.write_bytes(text.encode("latin-1"))
    with pytest.raises(FemError, match=message):
        read_tet_mesh(path)


@pytest.mark.parametrize("name", ["missing.mesh", "missing.vtu", "shape.obj"])
def test_missing_file_or_unknown_extension(tmp_path, name):
    with pytest.raises(FemError, match=re.escape(name)):
        read_tet_mesh(tmp_path / name)


@pytest.mark.parametrize("extension", [".msh", ".vtu", ".vtk", ".ele"])
def test_corrupt_meshio_file_is_a_fem_error(tmp_path, extension):
    path = tmp_path / f"bad{extension}"
    path.write_text("this is not a mesh\n")
    with pytest.raises(FemError, match=re.escape(path.name)):
        read_tet_mesh(path)


def test_meshio_file_without_tets_is_an_error(tmp_path):
    import meshio

    path = tmp_path / "surface.vtu"
    meshio.write(path, meshio.Mesh(UNIT_TET, [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(FemError, match=r"surface\.vtu: no tetrahedra"):
        read_tet_mesh(path)


# (vertices, tets) from the table in shared/cggs/README.md
COURSEWORK_COUNTS = {
    "tetrahedron": (4, 1), "octahedron": (6, 4), "box_tri": (11, 16),
    "long-octahedron": (18, 28), "cube86": (39, 86), "cyl248": (92, 248),
    "cylinder": (135, 432), "ellipsoid": (202, 658), "bunny": (358, 1196),
    "fertility": (777, 2546), "epcot": (1319, 4756), "cube_tri_refined": (1490, 6585),
}


@pytest.mark.skipif(not CGGS.is_dir(), reason=f"coursework meshes not present at {CGGS}")
@pytest.mark.parametrize("name", COURSEWORK_COUNTS)
def test_reads_coursework_mesh(name):
    mesh = read_tet_mesh(CGGS / f"{name}.mesh")
    assert (len(mesh.vertices), len(mesh.tets)) == COURSEWORK_COUNTS[name]
    assert (signed_volumes(mesh.vertices, mesh.tets) > 0).all()
