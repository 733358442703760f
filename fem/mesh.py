"""Tetrahedral meshes: the `TetMesh` container, checks, and file I/O.

Every mesh that enters the engine goes through `prepare_mesh`, so the rest of
the code can rely on three facts: coordinates are finite float64 metres,
indices are 0-based int32 in range, and every tet has a positive volume
(vertices ordered so that det([x0-x3, x1-x3, x2-x3]) > 0).

Files: MEDIT `.mesh` (the coursework format) has its own small parser so that
errors can name the line; `.msh`, `.vtk`, `.vtu` and TetGen `.node`/`.ele` go
through meshio.
"""

import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fem import limits
from fem.errors import FemError, excerpt, require_file


@dataclass
class TetMesh:
    """A tetrahedral mesh in its rest shape.

    vertices: (n, 3) float64, metres.
    tets: (m, 4) int32, 0-based vertex indices, every tet positively oriented.
    source: the file path or generator description, used in messages.
    """

    vertices: np.ndarray
    tets: np.ndarray
    source: str = ""


# Faces of a positively oriented tet (a, b, c, d), each listed counter-clockwise
# seen from outside, so the right-hand normal points out of the tet. Face k is
# the one opposite vertex k.
OUTWARD_FACES = np.array([[1, 3, 2], [0, 2, 3], [0, 3, 1], [0, 1, 2]])

# A tet is degenerate when |volume| <= VOLUME_TOLERANCE * (bbox diagonal)^3:
# relative, so the test means the same for a mesh in millimetres or in metres.
VOLUME_TOLERANCE = 1e-12

# The most tets one mesh may have; None: as many as the backend's memory holds
# (fem.limits.tet_limit: half of it, at about 550 bytes a tet in f32). A slip in a resolution
# (cells = [200, 200, 200]: 40 million tets) would otherwise take the machine's whole memory.
MAX_TETS = None

WRITE_FORMATS = {".mesh": "medit", ".msh": "gmsh", ".vtu": "vtu", ".vtk": "vtk"}
MESHIO_READ_EXTENSIONS = (".msh", ".vtk", ".vtu", ".node", ".ele")


def signed_volumes(vertices, tets):
    """Signed tet volumes det([x0-x3, x1-x3, x2-x3]) / 6.

    vertices: (n, 3) metres; tets: (m, 4) indices. Returns (m,) m^3, positive
    for positively oriented tets.
    """
    x = np.asarray(vertices, dtype=np.float64)[np.asarray(tets)]
    e0, e1, e2 = (x[:, i] - x[:, 3] for i in range(3))
    return np.einsum("ij,ij->i", e0, np.cross(e1, e2)) / 6.0


def dihedral_angles(vertices, tets):
    """The six dihedral angles of each tet, (m, 6) radians.

    The angle at the edge shared by faces i and j is pi minus the angle
    between their outward normals. A degenerate tet gives NaN.
    """
    x = np.asarray(vertices, dtype=np.float64)[np.asarray(tets)]
    # Angles do not change with scale: bring each tet to unit size so that
    # products of edge vectors neither overflow nor underflow.
    x = x - x[:, 3:4]
    with np.errstate(invalid="ignore", divide="ignore"):
        x /= np.abs(x).max(axis=(1, 2), keepdims=True)
    face = x[:, OUTWARD_FACES]                                   # (m, 4, 3, 3)
    normals = np.cross(face[:, :, 1] - face[:, :, 0], face[:, :, 2] - face[:, :, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    i, j = np.triu_indices(4, k=1)
    cosine = np.einsum("mkc,mkc->mk", normals[:, i], normals[:, j])
    return np.pi - np.arccos(np.clip(cosine, -1.0, 1.0))


def check_tet_count(count, source, what=None):
    """SizeLimitError naming `source` when a mesh of `count` tets would pass MAX_TETS, or the
    memory's limit (fem.limits.check_tets); --allow-large (limits.lifted) lifts it.

    what: how the count came about, for the message (default "{count} tets")."""
    limits.check_tets(count, source, what or f"{limits.amount(count)} tets", "per mesh", MAX_TETS)


def prepare_mesh(vertices, tets, source, *, tet_lines=None):
    """Check a raw mesh, orient every tet positively, and return a `TetMesh`.

    vertices: (n, 3) coordinates in metres; tets: (m, 4) 0-based indices.
    tet_lines: optional (m,) file line of each tet, so errors can name it.
    Raises FemError naming `source` (and the tet) for: wrong shapes, non-finite
    coordinates, non-integer or out-of-range indices, no tets, a vertex repeated
    within a tet, or a tet whose |volume| <= 1e-12 * bbox_diagonal^3.
    Negative tets are re-oriented by swapping their first two vertices.
    """
    def where(t):
        if tet_lines is None:
            return f"{source}: tet {t}"
        return f"{source}:{tet_lines[t]}: tet {t}"

    try:
        vertices = np.array(vertices, dtype=np.float64)
        tets = np.array(tets)
    except (TypeError, ValueError) as error:
        raise FemError(f"{source}: vertices or tets are not numeric arrays ({error})") from None
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise FemError(f"{source}: vertices must have shape (n, 3), got {vertices.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise FemError(f"{source}: tets must have shape (m, 4), got {tets.shape}")
    if len(tets) == 0:
        raise FemError(f"{source}: the mesh has no tetrahedra")
    check_tet_count(len(tets), source)

    bad_vertex = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if len(bad_vertex):
        raise FemError(f"{source}: vertex {bad_vertex[0]} has a non-finite coordinate")

    whole = tets.dtype.kind == "f" and np.isfinite(tets).all() and (tets == np.round(tets)).all()
    if whole and (np.abs(tets) < 2**31).all():
        tets = tets.astype(np.int64)
    if tets.dtype.kind not in "iu":
        raise FemError(f"{source}: tet vertex indices must be integers, got {tets.dtype}")
    n = len(vertices)
    out_of_range = np.flatnonzero(((tets < 0) | (tets >= n)).any(axis=1))
    if len(out_of_range):
        t = out_of_range[0]
        raise FemError(f"{where(t)} refers to vertices {tets[t].tolist()}, "
                       f"but the valid indices are 0..{n - 1}")
    tets = tets.astype(np.int32)

    sorted_tets = np.sort(tets, axis=1)
    repeated = np.flatnonzero((sorted_tets[:, 1:] == sorted_tets[:, :-1]).any(axis=1))
    if len(repeated):
        t = repeated[0]
        raise FemError(f"{where(t)} repeats a vertex: {tets[t].tolist()}")
    # Two copies of a tet share every face: such a mesh has no surface to draw or push.
    _, first, counts = np.unique(sorted_tets, axis=0, return_index=True, return_counts=True)
    if (counts > 1).any():
        copies = np.argmax(counts > 1)
        t = first[copies]
        raise FemError(f"{where(t)} (vertices {tets[t].tolist()}) appears {counts[copies]} times; "
                       f"{int((counts - 1).sum())} duplicate tet(s) in all")

    with np.errstate(over="ignore", invalid="ignore"):
        volumes = signed_volumes(vertices, tets)
        diagonal = np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0))
        tolerance = VOLUME_TOLERANCE * diagonal**3
    overflow = np.flatnonzero(~np.isfinite(volumes))
    if len(overflow) or not np.isfinite(tolerance):
        t = overflow[0] if len(overflow) else 0
        raise FemError(f"{where(t)}: coordinates too large to compute its volume")
    degenerate = np.flatnonzero(np.abs(volumes) <= tolerance)
    if len(degenerate):
        t = degenerate[0]
        raise FemError(f"{where(t)} (vertices {tets[t].tolist()}) has near-zero volume "
                       f"{volumes[t]:.3g} for a mesh {diagonal:.3g} across; {len(degenerate)} such tet(s) in all")

    negative = volumes < 0
    tets[negative, :2] = tets[negative, 1::-1]  # swapping two vertices flips the sign
    return TetMesh(vertices=vertices, tets=tets, source=str(source))


def boundary_faces(tets):
    """Faces used by exactly one tet, (k, 3) int32.

    tets: (m, 4) positively oriented. Each face is counter-clockwise seen from
    outside the mesh, so its right-hand normal points outward.
    """
    tets = np.asarray(tets)
    faces = tets[:, OUTWARD_FACES].reshape(-1, 3)
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0,
                                   return_inverse=True, return_counts=True)
    return faces[counts[inverse.reshape(-1)] == 1].astype(np.int32)


def mesh_quality(mesh):
    """Summary numbers for logs and tests.

    Returns {"tets", "vertices", "boundary_faces"} counts, "volume" (m^3) and
    "min_dihedral_deg" (the smallest dihedral angle of any tet, degrees).
    """
    return {
        "tets": len(mesh.tets),
        "vertices": len(mesh.vertices),
        "min_dihedral_deg": float(np.degrees(dihedral_angles(mesh.vertices, mesh.tets).min())),
        "volume": float(signed_volumes(mesh.vertices, mesh.tets).sum()),
        "boundary_faces": len(boundary_faces(mesh.tets)),
    }


def read_tet_mesh(path):
    """Read a tetrahedral mesh file into a checked `TetMesh`.

    `.mesh` (MEDIT ASCII) uses the parser below; `.msh`, `.vtk`, `.vtu` and
    TetGen `.node`/`.ele` use meshio. Coordinates are taken as metres.
    Raises FemError naming the file for anything it cannot use.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix != ".mesh" and suffix not in MESHIO_READ_EXTENSIONS:
        known = ", ".join([".mesh", *sorted(MESHIO_READ_EXTENSIONS)])
        raise FemError(f"{path}: unknown tet mesh extension {path.suffix!r} (known: {known})")
    require_file(path)
    from fem.limits import check_file_size
    check_file_size(path)
    if suffix == ".mesh":
        return _read_medit(path)
    return _read_with_meshio(path)


def write_tet_mesh(mesh, path):
    """Write `mesh` to `.mesh`, `.msh`, `.vtu` or `.vtk` through meshio.

    The file appears atomically: it is written under a temporary name in the
    same folder and then renamed, so a reader never sees half a file.
    """
    import meshio

    path = Path(path)
    file_format = WRITE_FORMATS.get(path.suffix.lower())
    if file_format is None:
        raise FemError(f"{path}: cannot write tet meshes with extension {path.suffix!r} "
                       f"(known: {', '.join(WRITE_FORMATS)})")
    # A clean Mesh with nothing but points and tets: extra point data (as gmsh
    # files carry) breaks meshio's MEDIT writer.
    clean = meshio.Mesh(np.asarray(mesh.vertices, dtype=np.float64),
                        [("tetra", np.asarray(mesh.tets, dtype=np.int64))])
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        meshio.write(temporary, clean, file_format=file_format)
        os.replace(temporary, path)
    except OSError as error:
        raise FemError(f"{path}: cannot write ({error.strerror})") from None
    finally:
        temporary.unlink(missing_ok=True)


def _read_with_meshio(path):
    import meshio

    # The format's own reader, not meshio.read: on a ReadError meshio.read
    # prints it and calls sys.exit.
    read = {".msh": meshio.gmsh.read, ".vtk": meshio.vtk.read, ".vtu": meshio.vtu.read,
            ".node": meshio.tetgen.read, ".ele": meshio.tetgen.read}[path.suffix.lower()]
    try:
        data = read(str(path))
    # meshio raises many types for bad files (ReadError, ValueError,
    # IndexError, struct.error, ...); each one means "this file is unusable".
    except Exception as error:
        detail = excerpt(str(error), 120) if str(error) else f"'not a valid {path.suffix} file'"
        raise FemError(f"{path}: cannot read ({type(error).__name__}: {detail})") from None
    other_solids = Counter(block.type for block in data.cells for _ in range(len(block.data))
                           if block.type != "tetra" and block.type.startswith(SOLID_CELLS))
    if other_solids:
        raise FemError(f"{path}: {cell_counts(other_solids)} besides tetrahedra: only 4-node tetrahedra are "
                       f"simulated, and dropping the others would lose their volume; split them into tets "
                       f"(e.g. Gmsh's Mesh > Subdivide or -format with linear tets) and save again")
    blocks = [block.data for block in data.cells if block.type == "tetra"]
    if not blocks:
        raise FemError(f"{path}: no tetrahedra in the file "
                       f"(cell types: {', '.join(b.type for b in data.cells) or 'none'})")
    return prepare_mesh(data.points, np.concatenate(blocks), str(path))


# meshio's names of 3-D cells (their higher-order kinds start the same): a file with one of these
# besides plain "tetra" is refused rather than simulated without it. Faces, edges and points
# (a Gmsh file's boundary and physical groups) are the tets' own boundary and are not needed.
SOLID_CELLS = ("tetra", "hexahedron", "wedge", "pyramid", "polyhedron")
# The MEDIT sections that hold 3-D cells other than 4-node tets.
MEDIT_OTHER_SOLIDS = {"hexahedra": "hexahedron", "prisms": "wedge", "pyramids": "pyramid",
                      "tetrahedrap2": "tetra10", "hexahedraq2": "hexahedron27"}


def cell_counts(counts):
    """'1 hexahedron cell, 2 wedge cells' from {cell type: count}."""
    return ", ".join(f"{n} {kind} cell{'s' if n != 1 else ''}" for kind, n in sorted(counts.items()))


def _read_medit(path):
    """Parse MEDIT ASCII: keyword sections, one entry per line.

    Keywords are case-insensitive; a count may sit on the keyword's line or the
    next one; trailing columns (the MEDIT `ref`) are ignored; sections other
    than Vertices and Tetrahedra are skipped. Indices are 1-based when the
    smallest one is 1 (as in the coursework reader), otherwise 0-based.
    """
    name = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FemError(f"{name}: not a text file (MEDIT .mesh must be ASCII)") from None
    except OSError as error:
        raise FemError(f"{name}: cannot read ({error.strerror})") from None

    lines = [(number, raw.split("#")[0].split())
             for number, raw in enumerate(text.splitlines(), start=1)]
    lines = [(number, tokens) for number, tokens in lines if tokens]
    if not lines:
        raise FemError(f"{name}: the file is empty")

    vertices = tets = None
    at = 0

    def read_count(keyword_at):
        """The section count after keyword line `keyword_at`; returns (count, next line)."""
        number, tokens = lines[keyword_at]
        if len(tokens) > 1:
            value, value_line, after = tokens[1], number, keyword_at + 1
        elif keyword_at + 1 < len(lines):
            value_line, value_tokens = lines[keyword_at + 1]
            value, after = value_tokens[0], keyword_at + 2
        else:
            raise FemError(f"{name}:{number}: the file ends after {excerpt(tokens[0])}, "
                           f"expected a count")
        try:
            count = int(value)
        except ValueError:
            count = -1
        if count < 0:
            raise FemError(f"{name}:{value_line}: {tokens[0]} count must be a "
                           f"non-negative integer, got {excerpt(value)}")
        return count, after

    def read_rows(keyword_at, what, width, convert):
        """`count` rows of at least `width` values after the keyword; returns (rows, row lines, next)."""
        keyword = lines[keyword_at][1][0]
        whats = "vertices" if what == "vertex" else f"{what}s"
        count, at = read_count(keyword_at)
        rows, row_lines = [], []
        for k in range(count):
            if at + k >= len(lines):
                raise FemError(f"{name}:{lines[keyword_at][0]}: {keyword} says {count} "
                               f"{whats} but the file ends after {k}")
            number, tokens = lines[at + k]
            try:
                values = [convert(token) for token in tokens[:width]]
            except ValueError as error:
                if _is_keyword(tokens[0]):
                    raise FemError(f"{name}:{number}: {keyword} says {count} {whats} but "
                                   f"{excerpt(tokens[0])} starts after {k}") from None
                raise FemError(f"{name}:{number}: {what} {k} {error}") from None
            if len(values) < width:
                raise FemError(f"{name}:{number}: {what} {k} has {len(values)} "
                               f"value(s), expected {width}")
            rows.append(values)
            row_lines.append(number)
        return rows, row_lines, at + count

    while at < len(lines):
        number, tokens = lines[at]
        keyword = tokens[0].lower()
        if not _is_keyword(tokens[0]):
            raise FemError(f"{name}:{number}: expected a keyword such as 'Vertices', got "
                           f"{excerpt(' '.join(tokens))} (does the count of the section "
                           f"above match its rows?)")
        if keyword == "end":
            break
        if keyword == "dimension":
            dimension, at = read_count(at)
            if dimension != 3:
                raise FemError(f"{name}:{number}: only 3-D meshes are supported, "
                               f"got Dimension {dimension}")
        elif keyword in ("vertices", "tetrahedra"):
            if (vertices if keyword == "vertices" else tets) is not None:
                raise FemError(f"{name}:{number}: a second {tokens[0]} section")
            if keyword == "vertices":
                rows, _, at = read_rows(at, "vertex", 3, _finite_float)
                vertices = np.array(rows, dtype=np.float64).reshape(-1, 3)
            else:
                rows, tet_lines, at = read_rows(at, "tet", 4, _index)
                tets = np.array(rows, dtype=np.int64).reshape(-1, 4)
        elif keyword in MEDIT_OTHER_SOLIDS:
            count, _ = read_count(at)
            if count:
                raise FemError(f"{name}:{number}: {tokens[0]}: {cell_counts({MEDIT_OTHER_SOLIDS[keyword]: count})} "
                               f"besides tetrahedra: only 4-node tetrahedra are simulated, and dropping the "
                               f"others would lose their volume; split them into tets and save again")
            at += 1
            while at < len(lines) and not _is_keyword(lines[at][1][0]):
                at += 1
        else:
            # MeshVersionFormatted, Triangles, Edges, Corners, ...: not needed.
            at += 1
            while at < len(lines) and not _is_keyword(lines[at][1][0]):
                at += 1

    if vertices is None:
        raise FemError(f"{name}: no Vertices section")
    if tets is None or len(tets) == 0:
        raise FemError(f"{name}: no tetrahedra (Tetrahedra section missing or empty)")

    one_based = tets.min() == 1
    largest = len(vertices) if one_based else len(vertices) - 1
    bad = np.flatnonzero((tets > largest).any(axis=1))
    if len(bad):
        t = bad[0]
        raise FemError(f"{name}:{tet_lines[t]}: tet {t} refers to vertex {tets[t].max()}, "
                       f"but the file has {len(vertices)} vertices "
                       f"({'1' if one_based else '0'}-based indices)")
    return prepare_mesh(vertices, tets - int(one_based), name, tet_lines=tet_lines)


def _is_keyword(token):
    """True for a section name such as 'Vertices' (but not for 'nan' or 'inf')."""
    try:
        float(token)
    except ValueError:
        return token[0].isalpha()
    return False


def _finite_float(token):
    try:
        value = float(token)
    except ValueError:
        raise ValueError(f"has a non-numeric coordinate {excerpt(token)}") from None
    if not np.isfinite(value):
        raise ValueError(f"has a non-finite coordinate {excerpt(token)}")
    return value


def _index(token):
    try:
        value = int(token)
    except ValueError:
        raise ValueError(f"has a vertex index {excerpt(token)} that is not an integer") from None
    # int32 is the engine's index type; the bound also keeps numpy from overflowing.
    if not 0 <= value < 2**31:
        raise ValueError(f"has an out-of-range vertex index {value}")
    return value
