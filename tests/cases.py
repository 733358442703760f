"""Running the hard cases, and bad inputs, defined once.

tests/test_hard_cases.py, tests/test_energy.py, tests/test_bad_input.py and
tools/robustness_table.py all read these lists, so the table in docs/robustness.md
always describes what the tests check. The hard cases themselves are
scenes/hard_cases.py (`main.py figures` draws one of them).

`run_hard_cases` runs the cases that share a time step and a step count as bodies of
one scene, and reports what each case did with each method (`Outcome`).

Bad inputs (`BAD_INPUTS`) are small files written into an empty folder plus the
`main.py simulate` arguments that read them, with the words the `error:` line
must contain.
"""

import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from scenes.hard_cases import (ENERGY_STEPS, GROUND_STEPS, HARD_CASES, METHODS, HardCase, build_scene, ground_scene,
                               mirror_inverted)

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Outcome:
    """What one hard case did with one method (numbers summed over its bodies)."""

    case: HardCase
    method: str
    finite: bool              # every position finite after every step
    energy_start: float       # J, kinetic + elastic + gravitational
    energy_end: float
    energy_max: float         # the largest total energy seen at any step
    inverted_start: int       # tets with det F <= 0
    inverted_end: int
    volume_ratio_end: list    # current / rest volume of each body
    rejected_steps: int       # steps rejected for non-finite values (whole scene)
    unconverged_steps: int    # steps whose solve stopped at the iteration cap (whole scene)
    max_iterations: int       # the most solver iterations of any step (whole scene)

    def summary(self):
        energy = f"energy {self.energy_start:.3g} -> {self.energy_end:.3g} J"
        parts = ["finite" if self.finite else "NOT FINITE", energy,
                 f"inverted {self.inverted_start} -> {self.inverted_end}",
                 "volume " + ", ".join(f"{r:.3f}" for r in self.volume_ratio_end)]
        return ", ".join(parts)


def run_hard_cases(cases, methods=METHODS):
    """Run cases that share dt and steps as one Simulation (fem.init must have been called).

    Returns [Outcome] in the order of `layout`: each case once per method.
    """
    import fem

    scene, layout = build_scene(cases, methods)
    sim = fem.Simulation(scene)
    mirror_inverted(sim, layout)

    def per_case(stats):
        energy = np.asarray(stats["body_total_energy"])
        inverted = np.asarray(stats["body_inverted_tets"])
        return ([float(energy[ids].sum()) for _, _, ids in layout],
                [int(inverted[ids].sum()) for _, _, ids in layout])

    energy_start, inverted_start = per_case(sim.stats())
    energy_max = list(energy_start)
    finite = [True] * len(layout)
    rejected = unconverged = most_iterations = 0
    sample = max(1, cases[0].steps // 100)      # energies every `sample` steps (stats cost a pass)
    for k in range(cases[0].steps):
        info = sim.step()
        rejected += not info["finite"]
        unconverged += not info["converged"]
        most_iterations = max(most_iterations, info["solver_iters"])
        if k % sample == sample - 1:
            energy, _ = per_case(sim.stats())
            energy_max = [max(a, b) for a, b in zip(energy_max, energy)]
            x = sim.positions()
            finite = [ok and bool(np.isfinite(x[vertex_range(sim, ids)]).all())
                      for ok, (_, _, ids) in zip(finite, layout)]
    stats = sim.stats()
    energy_end, inverted_end = per_case(stats)
    return [Outcome(case, method, finite[i], energy_start[i], energy_end[i], energy_max[i],
                    inverted_start[i], inverted_end[i], [stats["volume_ratio"][b] for b in ids],
                    rejected, unconverged, most_iterations)
            for i, (case, method, ids) in enumerate(layout)]


def energy_history(dt, steps=ENERGY_STEPS, methods=METHODS, integrator="backward-euler"):
    """Every hard case at time step dt for `steps` steps, in one Simulation (fem.init first).

    Returns (layout, energies, infos): energies (steps + 1, cases) is each case's total energy
    (J: kinetic + elastic + gravitational) at the start and after every step; infos, what
    each step did (Simulation.step).
    """
    import fem

    scene, layout = build_scene([replace(case, dt=dt, steps=steps) for case in HARD_CASES], methods)
    scene.solver.integrator = integrator
    sim = fem.Simulation(scene)
    mirror_inverted(sim, layout)
    return layout, *run_energies(sim, layout, steps)


def ground_history(dt, integrator="backward-euler", steps=None):
    """The ground drops (scenes/hard_cases.py: ground_scene) at time step dt; as energy_history,
    the energies (J) now with the contact's."""
    import fem

    scene, layout = ground_scene(dt, integrator)
    sim = fem.Simulation(scene)
    return layout, *run_energies(sim, layout, steps or GROUND_STEPS[dt])


def run_energies(sim, layout, steps):
    """(energies (steps + 1, cases), infos): each case's total energy before and after each step."""
    def per_case():
        energy = np.asarray(sim.stats()["body_total_energy"])
        return [float(energy[ids].sum()) for _, _, ids in layout]

    energies, infos = [per_case()], []
    for _ in range(steps):
        infos.append(sim.step())
        energies.append(per_case())
    return np.array(energies), infos


def vertex_range(sim, body_ids):
    """Global vertex ids of the given bodies."""
    return np.concatenate([np.arange(sim.model.bodies[b].vertices.start, sim.model.bodies[b].vertices.stop)
                           for b in body_ids])


# ---------------------------------------------------------------- solver failures, forced

def forced_failures(capture):
    """Force the two failures a step must report, on one small Simulation (fem.init first).

    1. The solve is capped at 2 iterations for a tolerance of 1e-12 (nu = 0.4999 needs dozens):
       every step must say converged False, 2 iterations, and its residual.
    2. NaN is written into one velocity: the step must be rejected, the positions kept, and a
       warning printed once however many steps fail.
    capture: returns the text printed on stderr since its last call.
    Returns {"capped": [step info], "nan": [step info], "before", "after": positions, "stderr": text}.
    """
    import fem

    scene, _ = build_scene([HARD_CASES[1]], ["corotational"])
    sim = fem.Simulation(scene, tolerance=1e-12, max_iterations=2, step="single")
    capped = [sim.step() for _ in range(3)]
    capture()
    v = sim.velocities()
    v[3] = np.nan
    sim.set_state(sim.positions(), v)   # a user writing into the state
    before = sim.positions()
    nan = [sim.step() for _ in range(3)]
    return {"capped": capped, "nan": nan, "before": before, "after": sim.positions(), "stderr": capture()}


# ---------------------------------------------------------------- hard cases through the command line

CLI_SCENE = """\
name = "extremes"
description = "near-incompressible, very stiff and very soft cubes, a 1e5 m/s impulse, dt 0.5 s"
[solver]
dt = 0.5
[effects]
damping = {{ alpha = 0.1, beta = 0.1 }}
[[body]]
name = "rubber"
mesh = {{ file = "cube.mesh" }}
material = {{ E = 1e4, nu = 0.4999, density = 1000.0 }}
method = "{method}"
[[body]]
name = "steel"
mesh = {{ file = "cube.mesh" }}
material = {{ E = 1e9, nu = 0.3, density = 8000.0 }}
position = [3.0, 0.0, 0.0]
method = "{method}"
[[body]]
name = "jelly"
mesh = {{ file = "cube.mesh" }}
material = {{ E = 10.0, nu = 0.3, density = 1000.0 }}
position = [6.0, 0.0, 0.0]
method = "{method}"
[[impulse]]
body = "rubber"
vertices = [0]
delta_v = [1e5, 0.0, 0.0]
[[impulse]]
body = "jelly"
vertices = [0]
delta_v = [0.0, 1e5, 0.0]
"""

# (method, precision): `main.py simulate extremes.toml` must finish with exit 0, every step kept
# and no NaN in its summary.
CLI_HARD_CASES = [("corotational", "f32"), ("linear", "f64")]




def run_cli_case(method, precision, folder, steps=10):
    """Run `main.py simulate` on CLI_SCENE in a fresh Python process; returns the CompletedProcess."""
    import subprocess

    (Path(folder) / "cube.mesh").write_text(CUBE_MESH)
    (Path(folder) / "extremes.toml").write_text(CLI_SCENE.format(method=method))
    return subprocess.run([sys.executable, str(ROOT / "main.py"), "simulate", "extremes.toml",
                           "--steps", str(steps), "--precision", precision],
                          cwd=folder, capture_output=True, text=True, timeout=300)


# ---------------------------------------------------------------- bad input

# A unit cube of 5 tets, MEDIT, 1-based; line 4 is "Vertices", lines 6-13 the vertices,
# line 14 "Tetrahedra", lines 16-20 the tets.
CUBE_MESH = """MeshVersionFormatted 1
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
Tetrahedra
5
1 2 3 5 0
4 2 3 8 0
6 2 5 8 0
7 3 5 8 0
2 3 5 8 0
End
"""

COURSEWORK_SCENE = """2
cube.mesh 100 1e4 0.3 0 0 3 0 1 0 0 0
cube.mesh 100 2e4 0.4 0 3 3 0 1 0 0 0
2
0 1 0 10 0
1 7 -10 0 0
"""

TOML_SCENE = """name = "two cubes"
[solver]
dt = 0.02
tolerance = 1e-4
[effects]
damping = { alpha = 0.1, beta = 0.1 }
[[body]]
name = "a"
mesh = { file = "cube.mesh" }
material = { E = 1e4, nu = 0.3, density = 100.0 }
[[initial]]
body = "a"
vertices = [1]
velocity = [0.0, 10.0, 0.0]
"""


def edit(text, line, new):
    """`text` with 1-based `line` replaced by `new` (None deletes it)."""
    lines = text.splitlines()
    lines[line - 1:line] = [] if new is None else [new]
    return "\n".join(lines) + "\n"


def replace_once(text, old, new):
    assert old in text, old
    return text.replace(old, new, 1)


@dataclass
class BadInput:
    """A broken file or parameter. files: {name: text} written into an empty folder;
    args: what follows `main.py simulate`; expect: words the error line must contain."""

    name: str
    files: dict
    args: list
    expect: list


def mesh_case(name, text, expect):
    return BadInput(name, {"cube.mesh": text, "s.toml": TOML_SCENE}, ["s.toml"], ["cube.mesh", *expect])


def toml_case(name, old, new, expect):
    return BadInput(name, {"cube.mesh": CUBE_MESH, "s.toml": replace_once(TOML_SCENE, old, new)},
                    ["s.toml"], ["s.toml", *expect])


def coursework_case(name, text, expect, mesh=CUBE_MESH):
    return BadInput(name, {"cube.mesh": mesh, "c-scene.txt": text}, ["c-scene.txt"], ["c-scene.txt", *expect])


def option_case(name, args, expect):
    return BadInput(name, {"cube.mesh": CUBE_MESH, "s.toml": TOML_SCENE}, ["s.toml", *args], expect)


BAD_INPUTS = [
    # .mesh files
    mesh_case("empty mesh file", "", ["empty"]),
    mesh_case("truncated mesh (ends inside Vertices)", "\n".join(CUBE_MESH.splitlines()[:9]) + "\n",
              [":4:", "8 vertices", "ends after 4"]),
    mesh_case("truncated mesh (ends inside a vertex line)", "\n".join(CUBE_MESH.splitlines()[:8]) + "\n0 1",
              [":9:", "vertex 3", "2 value"]),
    mesh_case("vertex count too large", edit(CUBE_MESH, 5, "9"), [":14:", "9 vertices", "'Tetrahedra'"]),
    mesh_case("vertex count too small", edit(CUBE_MESH, 5, "7"), [":13:", "keyword"]),
    mesh_case("tet count too large", edit(CUBE_MESH, 15, "6"), [":21:", "6 tet", "'End'"]),
    mesh_case("tet index out of range", edit(CUBE_MESH, 20, "2 3 5 9 0"), [":20:", "tet 4", "vertex"]),
    mesh_case("tet index 0 and 8 in a 1-based file", edit(CUBE_MESH, 16, "0 2 3 8 0"),
              [":16:", "tet 0", "vertex 8", "8 vertices"]),
    mesh_case("non-numeric coordinate", edit(CUBE_MESH, 7, "1 zero 0 1"), [":7:", "'zero'"]),
    mesh_case("NaN coordinate", edit(CUBE_MESH, 7, "1 nan 0 1"), [":7:", "non-finite", "'nan'"]),
    mesh_case("infinite coordinate", edit(CUBE_MESH, 7, "1 -inf 0 1"), [":7:", "non-finite"]),
    mesh_case("non-integer tet index", edit(CUBE_MESH, 16, "1 2 3.5 5 0"), [":16:", "'3.5'"]),
    mesh_case("zero-volume tet", edit(CUBE_MESH, 10, "0.5 0.5 0 1"), [":16:", "tet 0", "zero volume"]),
    mesh_case("tet repeating a vertex", edit(CUBE_MESH, 16, "1 2 2 5 0"), [":16:", "repeats"]),
    mesh_case("no Tetrahedra section", "\n".join(CUBE_MESH.splitlines()[:13]) + "\nEnd\n", ["no tet"]),
    # TOML scenes
    BadInput("scene file missing", {}, ["nothere.toml"], ["nothere.toml", "no such"]),
    BadInput("built-in scene name misspelt", {}, ["cube68"], ["cube68", "did you mean 'cube86'"]),
    toml_case("scene names a missing mesh", '"cube.mesh"', '"cubes.mesh"', ["cubes.mesh", "not found"]),
    toml_case("not TOML", "[solver]", "[solver", ["not valid TOML"]),
    toml_case("E = 0", "E = 1e4", "E = 0.0", ["E must be > 0"]),
    toml_case("E < 0", "E = 1e4", "E = -5e3", ["E must be > 0"]),
    toml_case("nu = 0.5", "nu = 0.3", "nu = 0.5", ["nu must be in (-1, 0.5)"]),
    toml_case("nu = -1", "nu = 0.3", "nu = -1.0", ["nu must be in (-1, 0.5)"]),
    toml_case("density = 0", "density = 100.0", "density = 0.0", ["density must be > 0"]),
    toml_case("dt = 0", "dt = 0.02", "dt = 0.0", ["dt must be > 0"]),
    toml_case("dt < 0", "dt = 0.02", "dt = -0.01", ["dt must be > 0"]),
    toml_case("tolerance = 0", "tolerance = 1e-4", "tolerance = 0.0", ["tolerance must be > 0"]),
    toml_case("misspelt key", "[effects]", "[efects]", ["unknown key 'efects'", "did you mean 'effects'"]),
    toml_case("misspelt material key", "E = 1e4", "young = 1e4", ["'young'"]),
    toml_case("wrong type: E is a string", "E = 1e4", 'E = "stiff"', ["E", "expected a number"]),
    toml_case("wrong type: dt is a list", "dt = 0.02", "dt = [0.02]", ["solver.dt", "expected a number"]),
    toml_case("wrong type: material is a number", "material = { E = 1e4, nu = 0.3, density = 100.0 }",
              "material = 5", ["material", "expected a table"]),
    toml_case("wrong type: dt is a string", "dt = 0.02", 'dt = "fast"', ["solver.dt", "expected a number"]),
    toml_case("initial velocity on a missing vertex", "vertices = [1]", "vertices = [99]",
              ["vertex 99 does not exist"]),
    toml_case("NaN in a TOML number", "dt = 0.02", "dt = nan", ["dt", "finite"]),
    toml_case("stick_speed = 0", "[effects]", "[effects]\nstick_speed = 0.0",
              ["effects.stick_speed", "must be in (0, 1]", "got 0.0"]),
    toml_case("stick_speed too fast", "[effects]", "[effects]\nstick_speed = 5.0",
              ["effects.stick_speed", "must be in (0, 1]", "got 5.0"]),
    # coursework scenes
    BadInput("coursework scene missing", {}, ["gone-scene.txt"], ["gone-scene.txt", "no such"]),
    coursework_case("coursework: mesh file missing", replace_once(COURSEWORK_SCENE, "cube.mesh", "gone.mesh"),
                    ["gone.mesh", "no such file"]),
    coursework_case("coursework: header promises 3 meshes, has 2", edit(COURSEWORK_SCENE, 1, "3"),
                    [":4:", "mesh line 3 of 3"]),
    coursework_case("coursework: header promises 3 impulses, has 2", edit(COURSEWORK_SCENE, 4, "3"),
                    ["impulse line 3 of 3", "line 4 promises"]),
    coursework_case("coursework: impulse on a vertex that does not exist", edit(COURSEWORK_SCENE, 6, "1 8 -10 0 0"),
                    [":6:", "vertex 8", "8 vertices"]),
    coursework_case("coursework: impulse on a mesh that does not exist", edit(COURSEWORK_SCENE, 6, "2 1 -10 0 0"),
                    [":6:", "mesh 2"]),
    coursework_case("coursework: E = 0", replace_once(COURSEWORK_SCENE, "1e4", "0"), [":2:", "E must be > 0"]),
    coursework_case("coursework: nu = 0.5", replace_once(COURSEWORK_SCENE, "0.3", "0.5"), [":2:", "nu must be"]),
    coursework_case("coursework: density < 0", replace_once(COURSEWORK_SCENE, "100", "-100"),
                    [":2:", "density must be > 0"]),
    coursework_case("coursework: non-numeric field", replace_once(COURSEWORK_SCENE, "1e4", "soft"),
                    [":2:", "'soft'"]),
    coursework_case("coursework: NaN field", replace_once(COURSEWORK_SCENE, "1e4", "nan"), [":2:", "finite"]),
    coursework_case("coursework: empty", "", ["ends early"]),
    coursework_case("coursework: mesh with a NaN vertex", COURSEWORK_SCENE, ["cube.mesh:7:", "non-finite"],
                    mesh=edit(CUBE_MESH, 7, "1 nan 0 1")),
    # command-line parameters
    option_case("--dt 0", ["--dt", "0"], ["--dt", "must be > 0"]),
    option_case("--dt -0.1", ["--dt", "-0.1"], ["--dt", "must be > 0"]),
    option_case("--tol 0", ["--tol", "0"], ["--tol", "must be > 0"]),
    option_case("--dt nan", ["--dt", "nan"], ["--dt", "must be > 0"]),
    option_case("--dt inf", ["--dt", "inf"], ["--dt", "must be > 0"]),
    option_case("--max-iters 0", ["--max-iters", "0"], ["--max-iters", "must be >= 1"]),
    option_case("--steps -1", ["--steps", "-1"], ["--steps", "must be >= 0"]),
    option_case("--set with an unknown key", ["--set", "solver.dtt=0.1"], ["unknown key 'dtt'", "did you mean 'dt'"]),
    option_case("--set E = -1", ["--set", "body.a.material.E=-1"], ["E must be > 0"]),
]


def run_bad_input(case, folder):
    """Write the case's files into the empty `folder` and run `main.py simulate` there, in this process.

    Returns (exit code, text printed on stderr).
    """
    import contextlib
    import io
    import os

    import main

    for name, text in case.files.items():
        (Path(folder) / name).write_text(text)
    stderr, cwd = io.StringIO(), os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            try:
                code = main.main(["simulate", "--steps", "1", *case.args])
            except SystemExit as exit:
                code = exit.code
    finally:
        os.chdir(cwd)
    return code, stderr.getvalue()
