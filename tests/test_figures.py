"""`main.py figures`: it writes each figure with the numbers behind it, those numbers are what
the engine's positions say and what docs/ holds, and bad input is one error line.

The torsion figures run at their committed length (the runs take seconds; Taichi's compiling
takes most of the time); the benchmark's plot is redrawn from a bench run in tests/test_bench.py.
"""

import contextlib
import io
import json

import numpy as np
import pytest
from conftest import ROOT

import main
from app.commands import figures
from scenes import load_scene

DOCS = ROOT / "docs"
PNG = b"\x89PNG"


def run(*argv):
    """main.main(argv) -> (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main.main(list(argv))
    return code, out.getvalue(), err.getvalue()


def tet_volumes(x, tets):
    """Signed volumes (m,) of tets (m, 4) at positions x (n, 3): det[x1 - x0, x2 - x0, x3 - x0] / 6."""
    a, b, c, d = (x[tets[:, i]] for i in range(4))
    return np.linalg.det(np.stack([b - a, c - a, d - a], axis=2)) / 6


def volume_ratios(scene, x):
    """Each body's volume over its rest volume, with the bodies' vertices one after another in x."""
    ratios, start = [], 0
    for body in scene.bodies:
        rest = body.mesh.vertices
        ratios.append(tet_volumes(x[start:start + len(rest)], body.mesh.tets).sum()
                      / tet_volumes(rest, body.mesh.tets).sum())
        start += len(rest)
    return ratios


def test_help_names_every_figure():
    code, out, _ = run("help", "figures")
    assert code == 0
    for figure in figures.catalogue():
        name = "volume_SCENE" if figure.name.startswith("volume_") else figure.name
        assert name in out, name
    assert "viewer.png" in out and "p key" in out      # the one figure in docs/ not made here


# ---------------------------------------------------------------- the numbers behind a figure

@pytest.fixture(scope="module")
def torsion(tmp_path_factory):
    """`figures --only volume_torsion torsion_length` as committed, and the runs it drew from:
    (folder, {method: (scene, positions at every sample)})."""
    out = tmp_path_factory.mktemp("figures")
    makers = []

    class Kept(figures.Maker):      # keeps the runs the command made
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            makers.append(self)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(figures, "Maker", Kept)
        code, out_text, err = run("figures", "--out", str(out), "--only", "volume_torsion", "torsion_length")
    assert code == 0, err
    assert "[1/2] volume_torsion" in err and "[2/2] torsion_length" in err
    assert "wrote 2 figures" in out_text
    (maker,) = makers
    scene = load_scene("torsion")
    return out, {method: (scene, maker.history("torsion", method, figures.DURATION_S).positions)
                 for method in ("linear", "corotational")}


def test_each_figure_is_a_png_and_its_numbers(torsion):
    out, _ = torsion
    assert sorted(p.name for p in out.iterdir()) == ["torsion_length.json", "torsion_length.png",
                                                     "volume_torsion.json", "volume_torsion.png"]
    for name in ("torsion_length", "volume_torsion"):
        assert (out / f"{name}.png").read_bytes().startswith(PNG)


def test_the_volume_plot_is_the_volume_of_the_positions(torsion):
    """Volume ratios recomputed with numpy from the positions and the scene's tets, sample by sample."""
    out, runs = torsion
    numbers = json.loads((out / "volume_torsion.json").read_text())
    assert numbers["t"][0] == 0 and numbers["t"][-1] == pytest.approx(figures.DURATION_S)
    for method, (scene, positions) in runs.items():
        plotted = numbers["volume_ratio"][method]["bar"]
        recomputed = [volume_ratios(scene, x)[0] for x in positions]
        np.testing.assert_allclose(plotted, recomputed, rtol=1e-5)
    linear, corotational = (numbers["volume_ratio"][m]["bar"] for m in ("linear", "corotational"))
    assert max(linear) > 2 and max(abs(v - 1) for v in corotational) < 0.1   # what the figure shows


def test_the_torsion_length_is_the_bars_extent_along_x(torsion):
    out, runs = torsion
    numbers = json.loads((out / "torsion_length.json").read_text())
    rest = load_scene("torsion").bodies[0].mesh.vertices
    assert numbers["axis"] == "x" and numbers["rest_length"] == pytest.approx(np.ptp(rest[:, 0]))
    for method, (_, positions) in runs.items():
        assert numbers["length"][method] == pytest.approx([x[:, 0].max() - x[:, 0].min() for x in positions])


@pytest.mark.parametrize("name", ["volume_torsion", "torsion_length"])
def test_the_committed_figure_has_the_same_numbers(torsion, name):
    """docs/ holds what `figures --out docs --overwrite` made from this engine: the same series,
    up to the solver's tolerance (regenerate docs/ when the engine changes them)."""
    out, _ = torsion
    made, committed = (json.loads(path.read_text()) for path in (out / f"{name}.json", DOCS / f"{name}.json"))
    assert made["t"] == pytest.approx(committed["t"])
    key = "volume_ratio" if name.startswith("volume") else "length"
    for method in ("linear", "corotational"):
        series = made[key][method]
        reference = committed[key][method]
        if key == "volume_ratio":
            series, reference = series["bar"], reference["bar"]
        # As tests/test_committed_figures.py: 5 % or 0.01. The linear bar's volume, grown past 2, differs
        # by 0.7 % between processors (0.0144 at t = 2.2 s here): f32 round-off in a long run.
        np.testing.assert_allclose(series, reference, rtol=0.05, atol=1e-2)


# ---------------------------------------------------------------- the benchmark's plot

# (redrawn from a bench run's results: tests/test_bench.py, beside that run)

def test_without_benchmark_results_the_accuracy_plot_is_skipped_with_a_reason(tmp_path):
    maker = figures.Maker(quick=True, cggs=None, bench_results=tmp_path / "no-docs" / "benchmark.json")
    made, skipped = figures.chosen(figures.catalogue(), None, maker)
    assert "accuracy_vs_time" not in [f.name for f in made]
    (why,) = [why for name, why in skipped if name == "accuracy_vs_time"]
    assert "benchmark.json not found" in why and "bench --docs" in why


# ---------------------------------------------------------------- the coursework's own scenes

def test_frame_25_of_the_coursework_scenes(cggs, tmp_path):
    code, _, err = run("figures", "--out", str(tmp_path), "--only", "frame25_coursework", "--cggs", str(cggs))
    assert code == 0, err
    from PIL import Image
    assert Image.open(tmp_path / "frame25_coursework.png").size == (800, 802)   # two 800 x 400 rows
    numbers = json.loads((tmp_path / "frame25_coursework.json").read_text())
    assert [s["scene"] for s in numbers["scenes"]] == ["epcot", "cube86"]
    for shown in numbers["scenes"]:
        assert shown["steps"] == 25 and shown["t"] == pytest.approx(25 * 0.02)
        linear, corotational = (list(shown["volume_ratio"][m].values()) for m in ("linear", "corotational"))
        assert max(abs(v - 1) for v in corotational) < 0.05
        assert max(abs(v - 1) for v in linear) > 2 * max(abs(v - 1) for v in corotational)


# ---------------------------------------------------------------- bad input

BAD = {
    "--out is a file": (["--out", "afile"], "--out"),
    "--out is not empty": (["--out", "full"], "--overwrite"),
    "--cggs folder missing": (["--out", "new", "--cggs", "no-such-folder"], "--cggs"),
    "--cggs without the scenes": (["--out", "new", "--cggs", "empty"], "epcot-scene.txt"),
    "--only an unknown figure": (["--out", "new", "--only", "volume_epcto"], "did you mean 'volume_epcot'"),
    "--only the coursework without --cggs": (["--out", "new", "--only", "frame25_coursework"], "--cggs"),
    "--bench file missing": (["--out", "new", "--bench", "nothing.json"], "--bench"),
}


@pytest.mark.parametrize("name", list(BAD))
def test_bad_input_is_one_error_line_and_exit_2_before_any_work(tmp_path, monkeypatch, name):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("mine")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.png").write_text("mine")
    (tmp_path / "empty").mkdir()
    argv, words = BAD[name]
    code, out, err = run("figures", *argv)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and words in lines[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "empty", "full"]   # nothing made
    assert (tmp_path / "full" / "keep.png").read_text() == "mine"

