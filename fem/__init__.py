"""softfem: linear and corotational tetrahedral FEM with an implicit, matrix-free solver.

    import fem
    from scenes import load_scene
    fem.init(arch="cpu", precision="f32")
    sim = fem.Simulation(load_scene("cube86"))
    for _ in range(50):
        sim.step()
    print(sim.stats()["volume_ratio"], sim.positions().shape)
"""

import os

__version__ = "0.1.0"

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")   # before taichi is first imported
from fem import environment  # noqa: E402

environment.prepare()                                       # also before taichi is first imported

from fem.errors import FemError  # noqa: E402
from fem.runtime import init, quick_declarations  # noqa: E402

quick_declarations()                                        # before any module declares a kernel
from fem.scene import Scene  # noqa: E402
from fem.simulation import Simulation  # noqa: E402

__all__ = ["__version__", "FemError", "Scene", "Simulation", "init"]
