"""Shared test fixtures: Taichi on the CPU, and small scenes built in Python."""

import os
import signal
from pathlib import Path

# Nine tenths of the suite's time was Taichi compiling kernels, not running them: each test builds
# small scenes once, and each new set of fields (precision, effects, size) compiles the step again.
# Taichi's IR optimisations off compiles a kernel in about 0.7 times the time (tests/test_trapezoidal.py
# with a cold cache: 134 -> 100 s) and runs it about 1.3 times slower (box50k: 51 -> 65 ms a step),
# to round-off the same results. Set before Taichi starts, so every test process and every command a
# test runs (they inherit this environment) compiles so; the app and the benchmark keep Taichi's
# default. TI_ADVANCED_OPTIMIZATION=1 in the environment tests the default build.
os.environ.setdefault("TI_ADVANCED_OPTIMIZATION", "0")

import numpy as np  # noqa: E402 (after the setting above)
import pytest  # noqa: E402

import fem  # noqa: E402
from fem.scene import Body, Effects, Material, Scene, SolverSettings  # noqa: E402
from scenes.hard_cases import cube  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CGGS = ROOT.parent / "shared" / "cggs"


def as_in_a_terminal():
    """preexec_fn of a run the tests interrupt: Ctrl-C, Ctrl-\\ and a closed terminal reach it as
    they do from a terminal, even when the suite runs in the background or under nohup (a shell
    starts background jobs with SIGINT and SIGQUIT ignored, nohup ignores SIGHUP, and children
    inherit what is ignored)."""
    for number in (signal.SIGINT, signal.SIGQUIT, signal.SIGHUP):
        signal.signal(number, signal.SIG_DFL)


@pytest.fixture(scope="module")
def f64():
    """Taichi on the CPU in double precision for this test module (restarts Taichi)."""
    fem.init("cpu", "f64")


@pytest.fixture
def f32():
    """Taichi on the CPU in single precision, as the command line runs it (a restart only after
    f64); a module running in f64 (the module-wide fixture above) gets it back after the test."""
    before = fem.runtime.current().get("precision")
    fem.init("cpu", "f32")
    yield
    if before == "f64":
        fem.init("cpu", "f64")


@pytest.fixture
def cggs():
    if not CGGS.is_dir():
        pytest.skip(f"coursework files not found at {CGGS} (they live beside the project, not in it)")
    return CGGS


def box_mesh(n=2, size=1.0):
    """A cube of n^3 cells, 6 tets each (Kuhn split), independent of assets/: the hard cases' cube."""
    return cube(cells=n, size=(size, size, size))


def make_scene(mesh, method="corotational", E=1e4, nu=0.3, density=1000.0, effects=None,
               solver=None, pinned=None, position=(0, 0, 0)):
    body = Body("box", type(mesh)(mesh.vertices + np.asarray(position), mesh.tets, mesh.source),
                Material(E, nu, density), method)
    if pinned is not None:
        body.pinned = np.asarray(pinned)
    return Scene("test", [body], effects=effects or Effects(),
                 solver=solver or SolverSettings(dt=0.01, tolerance=1e-10, max_iterations=500))


def fan_tets(vertices, faces, edge_length, path):
    """Stands in for wildmeshing (assets.tetrahedralize._run_wildmeshing) on a convex
    surface: one tet per triangle and the centre, instantly. Returns (vertices, tets)."""
    centre = len(vertices)
    return (np.vstack([vertices, vertices.mean(axis=0)]),
            np.hstack([faces, np.full((len(faces), 1), centre)]))


# pytest-xdist hands out whole files in the order they were collected; the longest start
# first, so that the processes finish together instead of one waiting on the last long file.
LONGEST_FIRST = ["test_hard_cases.py", "test_contact_hard.py", "test_bit_for_bit.py", "test_scenes.py", "test_energy.py", "test_solver.py", "test_coarse.py",
                 "test_figures.py", "test_sleep.py", "test_readme.py", "test_bench.py", "test_cli.py", "test_compile.py"]


def pytest_collection_modifyitems(session, config, items):
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONGEST_FIRST)))   # stable: each file's order kept
