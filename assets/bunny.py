"""The Stanford bunny, from the surface that ships in pybullet's wheel.

pybullet (zlib licence) carries `pybullet_data/bunny.obj`, a closed surface of
453 vertices and 902 triangles, y up, about 0.93 x 1.44 x 1.97 units. It is
tetrahedralised at first use and cached (see `assets.tetrahedralize`); the
package is only located, never imported.
"""

import importlib.metadata

from fem.errors import FemError
from fem.mesh import TetMesh

from assets.tetrahedralize import tetrahedralize_surface

# Metres per unit of bunny.obj: makes the bunny 0.72 m tall, with a bounding-box
# diagonal of 1.3 m, a size the default materials and time step suit.
SCALE = 0.5


def bunny_surface_path():
    """Path of pybullet's bunny.obj; FemError when pybullet is not installed."""
    try:
        distribution = importlib.metadata.distribution("pybullet")
    except importlib.metadata.PackageNotFoundError:
        raise FemError("the bunny comes from pybullet's data files: "
                       "install it with `pip install pybullet`") from None
    path = distribution.locate_file("pybullet_data/bunny.obj")
    if not path.is_file():
        raise FemError(f"pybullet is installed but {path} is missing")
    return path


def bunny(edge_length=0.05):
    """The Stanford bunny as a tet mesh, in metres (bunny.obj's units times 0.5).

    edge_length: target tet edge as a fraction of the bounding-box diagonal
    (0.05 gives about 3k tets). The first call for an edge_length takes a few
    seconds; later calls read the cache.
    """
    mesh = tetrahedralize_surface(bunny_surface_path(), edge_length)
    # Uniform positive scaling keeps every tet positively oriented.
    return TetMesh(mesh.vertices * SCALE, mesh.tets, f"bunny(edge_length={edge_length})")
