"""The pile at several sizes beside a peer (app/bench/contact.py, contact_report.py, gaps.py): the piles are
pile.toml's boxes, the gaps are distances, the rows say what was measured and what was not.

Timings are never asserted: they are what the benchmark measures.
"""

import importlib.util
import sys

import numpy as np
import pytest

import scenes
from app.bench import contact, contact_report, gaps
from app.bench.plan import PILE, full_plan

SCALING = {"sizes": [5, 40], "warmup": 40, "steps": 20, "load_average": [1.1, 1.3], "date": "2026-11-29",
           "distance": 0.01,
           "ours": [{"bodies": 5, "vertices": 135, "on": {"ms_median": 70.0, "newton": 7.5, "cg": 97.0,
                                                        "unconverged": 4, "gap": 0.0042, "crossed_steps": 0,
                                                        "sunk": 0.0012},
                     "off": {"ms_median": 3.5, "newton": 2.0, "cg": 10.0, "unconverged": 0}},
                    {"bodies": 40, "vertices": 1080, "on": {"ms_median": 1120.0, "newton": 19.0, "cg": 1500.0,
                                                          "unconverged": 12, "gap": None, "crossed_steps": 2,
                                                          "sunk": 0.0031},
                     "off": {"ms_median": 14.0, "newton": 3.0, "cg": 12.0, "unconverged": 1}}],
           "peer": {"rows": [{"bodies": 5, "contact_stiffness": 5e4, "ms_median": 539.0, "gap": 0.0006,
                              "crossed_steps": 0, "sunk": 0.01},
                             {"bodies": 5, "contact_stiffness": 1e6, "ms_median": 600.0, "gap": 0.008,
                              "crossed_steps": 0, "sunk": 0.0002},
                             {"bodies": 40, "contact_stiffness": 5e4, "ms_median": 900.0, "gap": 0.0015,
                              "crossed_steps": 0, "sunk": 0.018},
                             {"bodies": 40, "contact_stiffness": 1e6, "ms_median": 1200.0, "gap": None,
                              "crossed_steps": 3, "sunk": 0.0003}],
                    "setup": {"newton": "1.8.0", "warp": "1.19.0", "device": "cpu", "substeps": 10, "iterations": 15,
                              "particle_radius": 0.001}},
           "stick_speeds": {"bodies": 20, "rows": [
               {"stick_speed": 1e-3, "ms_median": 43.0, "newton": 15.7, "cg": 330.0, "unconverged": 1},
               {"stick_speed": 1e-2, "ms_median": 29.0, "newton": 9.7, "cg": 165.0, "unconverged": 0}]}}


def test_the_piles_are_pile_tomls_boxes_and_its_layers_repeated_above():
    toml = scenes.load_scene(PILE)
    boxes = toml.bodies
    for k in range(12, 20):          # pile.toml itself follows the rule its larger piles are made by
        assert np.allclose(boxes[k].mesh.vertices, boxes[k - 12].mesh.vertices + (0, contact.PERIOD_HEIGHT, 0))
    twenty = contact.pile(20)
    assert twenty.effects == toml.effects and twenty.solver == toml.solver
    assert same(twenty.bodies, boxes)
    forty = contact.pile(40)
    assert len(forty.bodies) == 40 and same(forty.bodies[:20], boxes)
    assert np.allclose(forty.bodies[39].mesh.vertices, boxes[15].mesh.vertices + (0, 2 * contact.PERIOD_HEIGHT, 0))
    assert same(contact.pile(5).bodies, boxes[:5])
    assert full_plan().contact_sizes == (5, 10, 20, 40)


def same(bodies, others):
    """Whether two lists of bodies have the same meshes, materials and methods."""
    return len(bodies) == len(others) and all(
        np.array_equal(a.mesh.vertices, b.mesh.vertices) and np.array_equal(a.mesh.tets, b.mesh.tets)
        and (a.material, a.method) == (b.material, b.method) for a, b in zip(bodies, others))


def test_the_gaps_are_distances_between_two_bodies_surfaces():
    """Two unit cubes of tets side by side 3 mm apart along x, the second shifted up half its height:
    nearest face to face, 3 mm; then pushed 2 mm into the first, a vertex of one lies inside the other."""
    toml = scenes.load_scene(PILE)
    cube = toml.bodies[0].mesh
    x0 = cube.vertices - cube.vertices.min(axis=0) + (0, 1, 0)
    width = np.ptp(x0[:, 0])
    x1 = x0 + (width + 0.003, 0.05, 0)
    surfaces = gaps.Surfaces(np.concatenate([cube.tets, cube.tets + len(x0)]), np.repeat([0, 1], len(x0)))
    measured = surfaces.measure(np.concatenate([x0, x1]), ground=1.01)
    assert measured["gap"] == pytest.approx(0.003) and not measured["crossed"]
    assert measured["sunk"] == pytest.approx(0.01)
    assert surfaces.measure(np.concatenate([x0, x1 - (0.005, 0, 0)]), ground=0)["crossed"]
    far = surfaces.measure(np.concatenate([x0, x1 + (1, 0, 0)]), ground=0)
    assert far == {"gap": None, "crossed": False, "sunk": 0.0}


def test_the_rows_give_ours_and_the_peers_cost_gap_and_depth():
    lines = contact_report.markdown(SCALING)
    text = "\n".join(lines)
    assert "| 5 | 135 | 70 | 7.5 | 97 | 4 of 20 | 3.5 | 20 x | 4.20 mm | 1.20 mm |" in lines
    assert "| 40 | 1080 | 1120 | 19.0 | 1500 | 12 of 20 | 14 | 80 x | crossed in 2 of 20 steps | 3.10 mm |" in lines
    at_five = lines.index("| 5 | ours | 70 | 4.20 mm | 1.20 mm |")
    assert lines[at_five + 1:at_five + 3] == ["| 5 | peer, 5e4 N/m | 539 | 0.60 mm | 10.00 mm |",
                                              "| 5 | peer, 1e6 N/m | 600 | 8.00 mm | 0.20 mm |"]
    assert "| 40 | peer, 1e6 N/m | 1200 | crossed in 3 of 20 steps | 0.30 mm |" in lines
    assert "The peer's (at 5e4 N/m) step costs 1.7 times as much at 40 boxes as at 5" in text
    assert "Our step costs 16.0 times as much at 40 boxes as at 5 (8 times the bodies): about bodies^1.33" in text
    assert "load average 1.1 at the start and 1.3 at the end" in text and "Newton 1.8.0's VBD" in text
    at = lines.index("### What friction's stick speed costs")
    assert "The pile of 20 boxes" in lines[at + 2] and "`[effects] stick_speed`" in lines[at + 2]
    assert lines[at + 6:at + 8] == ["| 1 mm/s | 43 | 15.7 | 330 | 1 of 20 |", "| 10 mm/s | 29 | 9.7 | 165 | 0 of 20 |"]
    old = {key: value for key, value in SCALING.items() if key != "stick_speeds"}      # measured before it had them
    assert contact_report.markdown(old) == lines[:at]
    results = {"contact": {**report_contact(), "scaling": SCALING}}
    assert contact_report.piles(results) == lines and contact_report.piles({"contact": report_contact()}) == []


def test_without_the_peer_its_rows_say_how_to_measure_it():
    lines = contact_report.markdown({**SCALING, "peer": contact.PEER_INSTALL})
    assert f"The peer, Newton's VBD: {contact.PEER_INSTALL}." in lines
    assert not any("| peer" in line for line in lines)
    assert "PEER_PYTHON" in contact.PEER_INSTALL and "pip install newton" in contact.PEER_INSTALL


def test_a_small_pile_is_measured_end_to_end(f32):
    """Two and three boxes, two steps after one: every figure there. The peer, asked of this Python
    (which has no `newton`), is reported as not measured, with why."""
    if importlib.util.find_spec("newton") is not None:
        pytest.skip("this Python has Newton: the peer would run")
    out = contact.scaling((2, 3), 1, 2, sys.executable)
    assert [r["bodies"] for r in out["ours"]] == [2, 3] and out["ours"][0]["vertices"] == 54
    for r in out["ours"]:
        assert r["on"]["ms_median"] > 0 and r["off"]["ms_median"] > 0 and r["on"]["newton"] >= 1
        assert r["on"]["crossed_steps"] == 0 and r["on"]["sunk"] >= 0
    assert out["peer"].startswith("not measured: ") and "No module named 'newton'" in out["peer"]
    assert len(out["load_average"]) == 2
    lines = contact_report.markdown(out)
    assert lines[0] == "### The pile from 2 to 3 boxes, beside a peer"
    assert f"The peer, Newton's VBD: {out['peer']}." in lines
    speeds = out["stick_speeds"]
    assert speeds["bodies"] == 3 and [r["stick_speed"] for r in speeds["rows"]] == list(contact.STICK_SPEEDS)
    assert all(r["newton"] >= 1 and r["ms_median"] > 0 for r in speeds["rows"])
    assert "### What friction's stick speed costs" in lines


def report_contact():
    """The profiled part of the contact section, as a benchmark before the piles had it."""
    return {"scene": "pile", "bodies": 20, "vertices": 540, "warmup": 40, "steps": 20, "machine": "AMD EPYC",
            "on": {"ms_median": 400.0, "newton": 17.0, "cg": 1200.0, "unconverged": 14, "pairs": 130.0,
                   "kernels": {"find": 0.01}, "share": 0.2},
            "off": {"ms_median": 8.0, "newton": 2.8, "cg": 12.0, "unconverged": 1}}
