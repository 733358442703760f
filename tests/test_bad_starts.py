"""Starts that contact cannot take (fem/contact_start.py), and a step that cannot be taken (issue 60,
items 4 and 5).

With contact on, bodies that start overlapping, one inside another, closer than the contact distance
(touching included), a body whose surface crosses itself, and a contact distance over a quarter of a
body are refused before any kernel compiles: through the command line with one `error:` line naming
the bodies and the depth or gap, exit code 2; through the Python API with a FemError. Bodies 1.5
contact distances apart start; without contact, overlapping bodies start (they pass through each
other by design). At dt 10 s on the ground, where the ground's penalty lets a resting body sink by
about 1 m a step, no step ends deep in the ground unsaid: it is split into sub-steps, and what is
still too deep is counted in the summary.
"""

import numpy as np
import pytest

import fem
import scenes
from app.commands.simulate import Tally, summary
from fem.builder import model_arrays, start_state
from fem.contact_start import check_start
from fem.errors import FemError
from fem.mesh import TetMesh, write_tet_mesh
from fem.simulation import SUNK
from scenes.hard_cases import cube
from test_cli import final_error_line, run

D_HAT = 0.01               # m, the contact distance of every scene here


def box(name, side, position):
    return (f'[[body]]\nname = "{name}"\nmesh = {{ generator = "box", size = [{side}, {side}, {side}], '
            f'cells = [1, 1, 1] }}\nmaterial = {{ E = 1e5, nu = 0.3 }}\nposition = [{", ".join(map(str, position))}]\n')


def scene_text(*bodies, contact=f"{{ distance = {D_HAT} }}", effects=""):
    return f"[effects]\n{effects}" + (f"contact = {contact}\n" if contact else "") + "".join(bodies)


# name: (scene text, words its error line holds). Boxes of 1 m, one above the other.
BAD_STARTS = {
    "overlapping": (scene_text(box("a", 1.0, (0, 0, 0)), box("b", 1.0, (0, 0.65, 0))),
                    ['bodies "a" and "b"', "overlapping", "350 mm along y"]),
    "one inside another": (scene_text(box("a", 1.0, (0, 0, 0)), box("b", 0.3, (0.1, 0.05, 0))),
                           ['body "b" starts inside body "a"', "550 mm along x"]),
    "touching": (scene_text(box("a", 1.0, (0, 0, 0)), box("b", 1.0, (0, 1.0, 0))),
                 ['bodies "a" and "b"', "0 mm apart", "contact distance (10 mm)"]),
    "closer than the contact distance": (scene_text(box("a", 1.0, (0, 0, 0)), box("b", 1.0, (0, 1.005, 0))),
                                         ['bodies "a" and "b"', "5 mm apart", "contact distance (10 mm)"]),
    "through itself": (scene_text('[[body]]\nname = "twins"\nmesh = { file = "two_cubes.mesh" }\n'
                                  'material = { E = 1e5, nu = 0.3 }\n'),
                       ['two pieces of body "twins"', "overlapping", "200 mm along x"]),
    "contact distance out of proportion": (scene_text(box("a", 1.0, (0, 0, 0)), box("b", 1.0, (0, 3.0, 0)),
                                                      contact="{ distance = 1000.0 }"),
                                           ['the contact distance', 'body "a"', "at most 250 mm"]),
}


@pytest.fixture
def scene_file(tmp_path, monkeypatch):
    """Writes a scene text as bad.toml in an empty current folder, beside two_cubes.mesh: two
    0.4 m cubes in one mesh, the second shifted by (0.2, 0.1, 0.05) m, so that they overlap."""
    monkeypatch.chdir(tmp_path)
    one = cube(cells=1, size=(0.4, 0.4, 0.4))
    vertices = np.concatenate([one.vertices, one.vertices + [0.2, 0.1, 0.05]])
    write_tet_mesh(TetMesh(vertices, np.concatenate([one.tets, one.tets + len(one.vertices)]), "two cubes"),
                   tmp_path / "two_cubes.mesh")

    def write(text):
        (tmp_path / "bad.toml").write_text(text)
        return "bad.toml"
    return write


def checked(path):
    """check_start on the scene at path, as the Simulation calls it: nothing compiled."""
    scene = scenes.load_scene(path)
    bodies, X, T, mass, free = model_arrays(scene)
    check_start(scene, start_state(scene, bodies, X, mass, free)[0], bodies, T)


@pytest.mark.parametrize("case", BAD_STARTS)
def test_a_bad_start_is_one_error_line_naming_the_bodies(scene_file, case):
    text, words = BAD_STARTS[case]
    code, out, err = run("simulate", scene_file(text), "--steps", "1")
    assert code == 2
    final_error_line(err, "error: bad.toml: ", *words)
    assert "scene" not in out                       # no summary: nothing ran


@pytest.mark.parametrize("case", BAD_STARTS)
def test_a_bad_start_is_a_fem_error_in_the_python_api(scene_file, case):
    text, words = BAD_STARTS[case]
    with pytest.raises(FemError) as error:
        fem.Simulation(scenes.load_scene(scene_file(text)))
    assert all(word in str(error.value) for word in words)
    assert "\n" not in str(error.value)


def test_one_and_a_half_contact_distances_apart_the_bodies_start(scene_file):
    """The positive control: 15 mm apart, one above the other, or side by side and turned."""
    checked(scene_file(scene_text(box("a", 1.0, (0, 0, 0)), box("b", 1.0, (0, 1.0 + 1.5 * D_HAT, 0)))))
    turned = box("b", 1.0, (1.0 + 1.5 * D_HAT, 0.2, 0.3)) + "rotation = [0.9659, 0.2588, 0.0, 0.0]\n"
    checked(scene_file(scene_text(box("a", 1.0, (0, 0, 0)), turned)))   # 30 deg about x: its faces stay 15 mm off


@pytest.mark.parametrize("case", [c for c in BAD_STARTS if c != "contact distance out of proportion"])
def test_without_contact_bodies_may_start_anywhere(scene_file, case):
    """Bodies pass through each other by design without contact: no start is refused for it."""
    text = BAD_STARTS[case][0].replace(f"contact = {{ distance = {D_HAT} }}\n", "")
    checked(scene_file(text))


def test_the_side_by_side_copies_and_the_contact_scenes_start():
    """Every built-in scene with --contact, and its --compare copy, starts (the hard cases'
    contact scenes are checked in tests/test_contact_hard.py, which builds them)."""
    for name in scenes.builtin_scenes():
        for scene in (scenes.load_scene(name, contact=True), scenes.load_scene(name, contact=True).side_by_side()):
            bodies, X, T, mass, free = model_arrays(scene)
            check_start(scene, start_state(scene, bodies, X, mass, free)[0], bodies, T)


DROP = scene_text(box("lower", 0.4, (0, 0.3, 0)), box("upper", 0.4, (0.05, 0.8, 0)),
                  contact=f"{{ distance = {D_HAT}, friction = 0.3 }}",
                  effects='gravity = [0.0, -9.81, 0.0]\nground = { height = 0.0, friction = 0.4 }\n')


def test_at_dt_10_s_nothing_sinks_into_the_ground_unsaid(scene_file, f32):
    """Two 0.4 m boxes dropped on the ground at dt 10 s: one step sank them 0.43 m (the lower box
    wholly below the ground) with a summary saying only "not converged". Now each step is split,
    and ends with every vertex within SUNK of its body's size of the ground, or is counted as
    failed, in its stats row and in the summary."""
    sim = fem.Simulation(scenes.load_scene(scene_file(DROP)), dt=10.0)
    size = sim.model.bodies[0].size
    rows = [sim.step() for _ in range(2)]
    x = sim.positions()
    assert all(row["finite"] for row in rows)
    assert all(row["substeps"] > 1 for row in rows)                  # split: one step of 10 s sinks too deep
    assert x[:, 1].min() > -SUNK * size or sim.ground_record["sunk_steps"] > 0
    assert x[:, 1].min() > -0.1                                       # m: not the 0.43 m of the unsplit step
    assert sim.ground_record["split_steps"] == 2
    assert sim.ground_record["sunk_steps"] == sum(row["sunk"] > 0 for row in rows)
    tally = Tally()
    tally += rows
    line = summary(sim, tally).splitlines()[-1]
    assert line.startswith("ground: 2 steps taken in sub-steps")
    assert f"{sim.ground_record['sunk_steps']} step" in line
