"""`main.py plot`: the numbers drawn are the numbers in the stats files, the picture is a PNG of
the size asked for, nothing is replaced without --overwrite, and a file that is not a stats file
is one `error:` line naming it. Taichi is never started."""

import json

import pytest
import taichi
from PIL import Image
from test_cli import one_error_line, run

from app.commands import plot

WIDTH = round(plot.WIDTH_IN * plot.DPI)
PANEL_HEIGHT = round(plot.PANEL_HEIGHT_IN * plot.DPI)


def write_stats(path, rows):
    path.write_text("".join(json.dumps(row) + "\n" for row in rows))
    return path


def known_rows(steps=10, scale=1.0):
    """Rows like simulate's, with numbers easy to check: total_energy = 2 t (times scale)."""
    rows = []
    for step in range(1, steps + 1):
        t = 0.1 * step
        rows.append({"step": step, "t": t, "solver": "pcg", "newton_iters": 1 + step % 3,
                     "solver_iters": 10 * step, "residual": 10.0 ** -step, "kinetic_energy": scale * 1.5 * t,
                     "elastic_energy": scale * 0.5 * t, "total_energy": scale * 2 * t,
                     "volume_ratio": [1.0, 1.0 + t], "converged": True})
    return rows


def curves(numbers, panel, key, file=None):
    return [c for c in numbers["panels"][panel]["curves"] if c["key"] == key and file in (None, c["file"])]


@pytest.fixture
def here(tmp_path, monkeypatch):
    """An empty current folder, in which starting Taichi fails the test."""
    monkeypatch.chdir(tmp_path)

    def no_taichi(*args, **kwargs):
        raise AssertionError("plot started Taichi")

    monkeypatch.setattr(taichi, "init", no_taichi)
    return tmp_path


def test_the_numbers_drawn_are_the_numbers_in_the_file(here):
    write_stats(here / "run.jsonl", known_rows())
    code, out, err = run("plot", "run.jsonl")
    assert code == 0, err
    assert "run.png" in out and err == ""
    numbers = json.loads((here / "run.json").read_text())     # beside the stats file, as NAME.png
    assert list(numbers["panels"]) == ["energy", "volume_ratio", "iterations", "residual"]
    assert numbers["files"] == {"run.jsonl": "run.jsonl"}
    t = [0.1 * step for step in range(1, 11)]
    energy = {c["key"]: c for c in numbers["panels"]["energy"]["curves"]}
    assert list(energy) == ["kinetic_energy", "elastic_energy", "total_energy"]     # the terms it has, the total
    assert energy["total_energy"]["t"] == pytest.approx(t)
    assert energy["total_energy"]["y"] == pytest.approx([2 * x for x in t])
    assert energy["kinetic_energy"]["y"] == pytest.approx([1.5 * x for x in t])
    bodies = curves(numbers, "volume_ratio", "volume_ratio")
    assert [c["body"] for c in bodies] == [0, 1]
    assert bodies[0]["y"] == pytest.approx([1.0] * 10) and bodies[1]["y"] == pytest.approx([1 + x for x in t])
    assert curves(numbers, "iterations", "solver_iters")[0]["y"] == [10.0 * s for s in range(1, 11)]
    assert curves(numbers, "iterations", "newton_iters")[0]["y"] == [1.0 + s % 3 for s in range(1, 11)]
    assert numbers["panels"]["residual"]["scale"] == "log"
    assert curves(numbers, "residual", "residual")[0]["y"] == pytest.approx([10.0 ** -s for s in range(1, 11)])
    with Image.open(here / "run.png") as image:
        assert image.format == "PNG" and image.size == (WIDTH, 4 * PANEL_HEIGHT)
        image.verify()


def test_several_files_are_drawn_over_each_other_each_named(here):
    write_stats(here / "single.jsonl", known_rows(scale=3.0))
    (here / "b").mkdir()
    write_stats(here / "b" / "newton.jsonl", known_rows(steps=4))
    code, _, err = run("plot", "single.jsonl", "b/newton.jsonl", "--quantity", "total_energy",
                       "--out", "out/e.png")
    assert code == 0, err
    numbers = json.loads((here / "out" / "e.json").read_text())
    assert list(numbers["panels"]) == ["total_energy"]
    single, newton = (curves(numbers, "total_energy", "total_energy", file)[0]
                      for file in ("single.jsonl", "newton.jsonl"))
    assert single["y"] == pytest.approx([6 * 0.1 * s for s in range(1, 11)])
    assert newton["y"] == pytest.approx([2 * 0.1 * s for s in range(1, 5)])
    with Image.open(here / "out" / "e.png") as image:
        assert image.size == (WIDTH, PANEL_HEIGHT)


def test_a_gap_where_a_row_has_no_number(here):
    rows = known_rows(steps=3)
    rows[1]["residual"] = None           # simulate writes null for a residual that is not finite
    write_stats(here / "s.jsonl", rows)
    assert run("plot", "s.jsonl", "--quantity", "residual")[0] == 0
    numbers = json.loads((here / "s.json").read_text())
    assert curves(numbers, "residual", "residual")[0]["y"] == [0.1, None, 0.001]


def test_an_existing_picture_is_replaced_only_with_overwrite(here):
    write_stats(here / "s.jsonl", known_rows(steps=3))
    (here / "s.png").write_text("my own picture")
    code, out, err = run("plot", "s.jsonl")
    assert code == 2 and out == ""
    one_error_line(err, "s.png", "--overwrite")
    assert (here / "s.png").read_text() == "my own picture" and not (here / "s.json").exists()
    assert run("plot", "s.jsonl", "--overwrite")[0] == 0
    with Image.open(here / "s.png") as image:
        assert image.format == "PNG"


BAD = {
    "no such file": ([], ["plot", "gone.jsonl"], ["gone.jsonl", "no such file"]),
    "a folder": ([], ["plot", "folder"], ["folder", "is a folder"]),
    "a device": ([], ["plot", "/dev/zero"], ["/dev/zero", "is a character device, not a file"]),
    "an empty file": ([("empty.jsonl", "")], ["plot", "empty.jsonl"], ["empty.jsonl", "empty"]),
    "a line not JSON": ([("s.jsonl", '{"t": 0.1}\n{"t": 0.2, oops\n')], ["plot", "s.jsonl"],
                        ["s.jsonl:2:", "not a line of JSON"]),
    "a row without t": ([("s.jsonl", '{"t": 0.1}\n\n{"time": 0.2}\n')], ["plot", "s.jsonl"],
                        ["s.jsonl:3:", "'t'"]),
    "an unknown quantity": ([("s.jsonl", '{"t": 0.1, "total_energy": 1}\n')],
                            ["plot", "s.jsonl", "--quantity", "total_enrgy"],
                            ["s.jsonl", "total_enrgy", "did you mean total_energy?"]),
    "a quantity that is no number": ([("s.jsonl", '{"t": 0.1, "solver": "pcg"}\n')],
                                     ["plot", "s.jsonl", "--quantity", "solver"],
                                     ["s.jsonl:1:", "solver", "not a number"]),
    "a picture that is not a PNG": ([("s.jsonl", '{"t": 0.1, "total_energy": 1}\n')],
                                    ["plot", "s.jsonl", "--out", "s.svg"], ["s.svg", ".png"]),
    "numbers over a stats file": ([("s.json", '{"t": 0.1, "total_energy": 1}\n')], ["plot", "s.json"],
                                  ["s.json", "another --out"]),
}


@pytest.mark.parametrize("name", BAD)
def test_bad_input_is_one_error_line_naming_the_file(here, name):
    files, argv, words = BAD[name]
    (here / "folder").mkdir()
    for file, text in files:
        (here / file).write_text(text)
    before = sorted(here.iterdir())
    code, out, err = run(*argv)
    assert code == 2 and out == ""
    one_error_line(err, *words)
    assert "Traceback" not in err
    assert sorted(here.iterdir()) == before          # nothing written


def test_plot_draws_what_simulate_wrote(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = run("simulate", "torsion", "--steps", "3", "--stats", "torsion.jsonl")
    assert code == 0, err
    rows = [json.loads(line) for line in (tmp_path / "torsion.jsonl").read_text().splitlines()]
    code, _, err = run("plot", "torsion.jsonl")
    assert code == 0, err
    numbers = json.loads((tmp_path / "torsion.json").read_text())
    assert list(numbers["panels"]) == ["energy", "volume_ratio", "iterations", "residual"]
    total = curves(numbers, "energy", "total_energy")[0]
    assert total["t"] == pytest.approx([row["t"] for row in rows])
    assert total["y"] == pytest.approx([row["total_energy"] for row in rows])
    volume = curves(numbers, "volume_ratio", "volume_ratio")[0]
    assert volume["y"] == pytest.approx([row["volume_ratio"][0] for row in rows])
    with Image.open(tmp_path / "torsion.png") as image:
        assert image.size == (WIDTH, 4 * PANEL_HEIGHT)
