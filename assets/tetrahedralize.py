"""Closed surface (OBJ, STL, PLY) -> tet mesh, with wildmeshing and a cache.

Tetrahedralising takes seconds, so the result is stored in a user cache
directory, keyed by the input file's bytes and the parameters; later calls
load it in milliseconds. The cache lives outside the repository: a mesh made
from someone else's surface is never committed.
"""

import contextlib
import hashlib
import importlib.util
import math
import os
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

from fem.errors import FemError, excerpt
from fem.limits import amount, check_file_size
from fem.mesh import check_tet_count, prepare_mesh

# Bump when the output for the same input changes (tool, options, file layout),
# so old cache entries are no longer found.
CACHE_FORMAT = "wildmeshing-0.4.1/v1"

# Tets from an edge length (a fraction of the bounding-box diagonal): about
# TETS_AT_5_PERCENT at 0.05 for a compact shape such as the bunny, growing as 1/edge^3.
TETS_AT_5_PERCENT = 3000

# True when the latest tetrahedralize_surface call was served from the cache.
last_cache_hit = False


def cache_dir():
    """$FEM_CACHE_DIR if set, else $XDG_CACHE_HOME/softfem, else ~/.cache/softfem."""
    if os.environ.get("FEM_CACHE_DIR"):
        return Path(os.environ["FEM_CACHE_DIR"])
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "softfem"


def tetrahedralize_surface(path, edge_length=0.05, progress=True):
    """Tet mesh filling the closed triangle surface in `path`.

    edge_length: the target tet edge length as a fraction of the surface's
    bounding-box diagonal (wildmeshing's `edge_length_r`; 0.05 gives a few
    thousand tets). Coordinates keep the file's units. progress: print what
    is happening and how long it took to stderr when the cache is missed.
    wildmeshing is not bit-for-bit repeatable between runs; the cache makes
    repeated calls on one machine return the same mesh.
    """
    global last_cache_hit
    path = Path(path)
    if not (isinstance(edge_length, (int, float)) and 0 < edge_length <= 1):
        raise FemError(f"{path}: edge_length must be a fraction in (0, 1] of the bounding-box "
                       f"diagonal, got {edge_length!r}")
    check_file_size(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise FemError(f"{path}: cannot read ({error.strerror})") from None

    key = hashlib.sha256(data)
    key.update(f"|{path.suffix.lower()}|edge_length={float(edge_length)!r}|{CACHE_FORMAT}"
               .encode())
    cached = cache_dir() / f"{key.hexdigest()}.npz"
    source = f"{path} (tetrahedralised, edge_length={edge_length})"

    mesh = (cached_mesh(cached, source) or [None])[0]
    last_cache_hit = mesh is not None
    if mesh is None:
        estimate = round(TETS_AT_5_PERCENT * (0.05 / edge_length) ** 3)
        check_tet_count(estimate, path, f"edge_length {edge_length} gives about {amount(estimate)} tets")
        start = time.perf_counter()
        vertices, faces = load_surface(path)
        if progress:
            print(f"tetrahedralising {path.name} ({len(faces)} triangles) with wildmeshing, "
                  f"edge length {edge_length} x bbox diagonal ...", file=sys.stderr, flush=True)
        mesh = prepare_mesh(*_run_wildmeshing(vertices, faces, edge_length, path), source)
        write_cache_entry(cached, (mesh.vertices, mesh.tets))    # only a mesh that passed the checks
        if progress:
            print(f"  done in {time.perf_counter() - start:.1f} s: {len(mesh.tets)} tets, "
                  f"{len(mesh.vertices)} vertices; cached in {cached}", file=sys.stderr)
    return mesh


def cached_mesh(cached, source, *names):
    """(the checked TetMesh in a cache entry, *its arrays `names`), or None when
    the entry is absent, damaged, altered or not a valid mesh: then it is rebuilt. An entry
    is trusted no more than a mesh file (a vertex index of -1408 would read outside the
    engine's fields)."""
    arrays = read_cache_entry(cached, *names)
    if arrays is None:
        return None
    try:
        return (prepare_mesh(arrays[0], arrays[1], source), *arrays[2:])
    except FemError:
        return None


def checksum(*arrays):
    """sha256 of arrays' dtypes, shapes and bytes: what a cache entry must still match."""
    digest = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def read_cache_entry(cached, *names):
    """(vertices, tets, *names) from a cache file, or None when it is absent, unreadable or
    does not match the checksum written with it."""
    if not Path(cached).is_file():      # absent, or a FIFO or device, which would block or never end
        return None
    try:
        with np.load(cached, allow_pickle=False) as data:
            arrays = tuple(data[name] for name in ("vertices", "tets", *names))
            stored = str(data["checksum"])
    # A damaged cache entry (truncated: not a zip file any more) is rebuilt, not reported:
    # the cache is disposable.
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None
    return arrays if stored == checksum(*arrays[:2]) else None


def write_cache_entry(cached, arrays, **more):
    """Write the cache entry atomically, with the checksum of its vertices and tets; a cache
    that cannot be written is only a warning."""
    temporary = None
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=cached.parent, suffix=".tmp",
                                         delete=False) as file:
            temporary = file.name
            np.savez(file, vertices=arrays[0], tets=arrays[1], checksum=np.array(checksum(*arrays[:2])),
                     **more)
        os.replace(temporary, cached)
    except OSError as error:
        print(f"warning: could not cache the tet mesh in {cached.parent}: {error}",
              file=sys.stderr)
        if temporary is not None:       # a full disk, or a folder where the entry goes: no leftovers
            with contextlib.suppress(OSError):
                os.unlink(temporary)


def load_surface(path):
    """(n, 3) float64 vertices and (f, 3) int32 triangles of a surface file."""
    import trimesh

    check_file_size(Path(path))
    try:
        surface = trimesh.load(path, force="mesh")
    # trimesh raises many types for unreadable files; each means "not a surface". (For
    # random bytes it may even fail to import an optional text-encoding module.)
    except ImportError:
        raise FemError(f"{path}: cannot read a surface (not a valid {Path(path).suffix} file)") from None
    except Exception as error:
        why = obj_line_problem(path) or f"{type(error).__name__}: {excerpt(error, 120)}"
        raise FemError(f"{path}: cannot read a surface ({why})") from None
    faces = np.asarray(getattr(surface, "faces", np.zeros((0, 3))))
    if faces.ndim != 2 or len(faces) == 0:
        raise FemError(f"{path}: no triangles in the file")
    vertices = np.asarray(surface.vertices, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:   # trimesh reads an .obj of 'v x y' lines as 2-D
        why = obj_line_problem(path) or f"its vertices have {vertices.shape[-1]} coordinates, not 3"
        raise FemError(f"{path}: cannot read a surface ({why})")
    if not np.isfinite(vertices).all():
        raise FemError(f"{path}: the surface has non-finite coordinates")
    faces = faces.astype(np.int32)
    open_edges = count_open_edges(faces)
    if open_edges:
        raise FemError(f"{path}: the surface is not closed: {open_edges} edges have a triangle on one side "
                       "only (a hole); only a closed surface has an inside to fill with tets")
    return vertices, faces


def obj_line_problem(path):
    """For a Wavefront .obj that trimesh could not read: the first vertex line without three
    numbers ("line 4: a vertex needs x y z, got 'v 1 2'"), or None. (trimesh's own error for it
    is numpy's: "operands could not be broadcast together".)"""
    if Path(path).suffix.lower() != ".obj":
        return None
    try:
        lines = Path(path).read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return None
    for number, line in enumerate(lines, start=1):
        tokens = line.split("#")[0].split()
        if tokens[:1] != ["v"]:
            continue
        try:
            ok = len(tokens) >= 4 and all(math.isfinite(float(t)) for t in tokens[1:4])
        except ValueError:
            ok = False
        if not ok:
            return f"line {number}: a vertex needs x y z, got {excerpt(line.strip(), 60)}"
    return None


def count_open_edges(faces):
    """How many edges of a triangle surface (f, 3) belong to exactly one triangle: 0 for a
    closed surface."""
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    return int((uses == 1).sum())


# Runs in a child process, in a temporary folder: wildmeshing prints its
# progress on stdout (partly from a background thread) and writes
# __tracked_surface.stl into the working directory, and a crash in the C++
# code must not take the caller down with it.
WILDMESHING_SCRIPT = """
import sys
import numpy as np
import wildmeshing

surface = np.load("surface.npz")
tetrahedralizer = wildmeshing.Tetrahedralizer(edge_length_r=float(sys.argv[1]), max_threads=1)
tetrahedralizer.set_mesh(surface["vertices"], surface["faces"])
tetrahedralizer.tetrahedralize()
vertices, tets = tetrahedralizer.get_tet_mesh()[:2]
np.savez("tets.npz", vertices=vertices, tets=tets)
"""


def _run_wildmeshing(vertices, faces, edge_length, path):
    """Tetrahedralise with wildmeshing in a child process; returns (vertices, tets)."""
    if importlib.util.find_spec("wildmeshing") is None:
        raise FemError(f"{path}: tetrahedralising a surface needs wildmeshing: "
                       f"install it with `pip install wildmeshing`")
    with tempfile.TemporaryDirectory() as work:
        np.savez(Path(work) / "surface.npz", vertices=vertices, faces=faces)
        result = subprocess.run([sys.executable, "-c", WILDMESHING_SCRIPT, str(edge_length)],
                                cwd=work, capture_output=True, text=True)
        if result.returncode != 0:
            tail = (result.stderr or result.stdout).strip().splitlines()[-3:]
            raise FemError(f"{path}: wildmeshing failed (exit code {result.returncode}): "
                           f"{' | '.join(tail)}")
        with np.load(Path(work) / "tets.npz") as output:
            return output["vertices"].astype(np.float64), output["tets"].astype(np.int32)
