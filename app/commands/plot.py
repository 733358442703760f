"""`main.py plot`: draw the rows that `main.py simulate --stats` wrote, against time.

    python main.py plot out/s.jsonl                               # out/s.png, its numbers in out/s.json
    python main.py plot out/single.jsonl out/newton.jsonl --out out/dt-energy.png
    python main.py plot out/s.jsonl --quantity total_energy volume_ratio

The panels, one above the other, share the time axis t: the energy terms each file has and
their total, the volume ratio of each body, the Newton and linear solver (CG) iterations of
each step, and the residual each step ended with (log axis). --quantity draws the named keys
of the rows instead, one panel each. Several files are drawn over each other, each line
labelled with its file's name: the same key has one colour, each file its own line style.

Like every figure of the project, the picture NAME.png comes with NAME.json, the numbers drawn
in it. The command only reads files: Taichi is never started.
"""

import difflib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from app.files import atomic_open, check_output, refuse_overwrite
from fem.errors import FemError, excerpt, not_a_file

WIDTH_IN, PANEL_HEIGHT_IN, DPI = 7.0, 2.2, 100      # the picture: 700 pixels wide, 220 a panel
LINE_STYLES = ("-", "--", ":", "-.")                 # file i draws with LINE_STYLES[i % 4]


@dataclass
class Stats:
    """One stats file: `rows`, the JSON object of each of its lines, and `line_numbers`, the
    line each row came from (for messages); `label` names the file in the legend."""

    path: Path
    rows: list
    line_numbers: list
    label: str = ""

    def has(self, key) -> bool:
        return any(key in row for row in self.rows)

    def column(self, key) -> list[list[float]]:
        """The curves `key` draws: one for a number per row, one per body for a list per row
        (volume_ratio); NaN, a gap, where a row lacks the key or holds null."""
        values = [row.get(key) for row in self.rows]
        bodies = max((len(v) for v in values if isinstance(v, list)), default=0)
        if bodies == 0:
            return [[self.number(key, v, i) for i, v in enumerate(values)]]
        return [[self.number(key, v[b] if isinstance(v, list) and b < len(v) else None, i)
                 for i, v in enumerate(values)] for b in range(bodies)]

    def number(self, key, value, row) -> float:
        if value is None:
            return math.nan
        if not isinstance(value, (int, float)):
            where = f"{self.path}:{self.line_numbers[row]}"
            raise FemError(f"{where}: {key} is {excerpt(json.dumps(value))}, not a number")
        return to_float(value)


def to_float(value) -> float:
    """A JSON number as a float; an integer too large for one is infinite (as a blown-up run's is)."""
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


@dataclass
class Panel:
    """One axes of the picture: its y label, the keys it draws, and its y scale."""

    ylabel: str
    keys: list
    scale: str = "linear"
    curves: list = field(default_factory=list)    # what was drawn, for NAME.json


def read_stats(path) -> Stats:
    """The rows of a stats file, one JSON object a line; blank lines are skipped. FemError,
    naming the file (and line), for anything that is not such a file."""
    path = Path(path)
    reason = not_a_file(path)           # a folder, a device (/dev/zero: read for ever), a link that loops
    if reason == "no such file":
        raise FemError(f"{path}: no such file")
    if reason:
        raise FemError(f"{path}: is {reason}; give a stats file (`simulate --stats FILE.jsonl` writes one)")
    try:
        text = path.read_text(errors="replace")
    except OSError as error:
        raise FemError(f"{path}: cannot read ({error.strerror})") from None
    stats = Stats(path, [], [])
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except ValueError:
            raise FemError(f"{path}:{number}: not a line of JSON: {excerpt(line)}") from None
        if not isinstance(row, dict):
            raise FemError(f"{path}:{number}: not a JSON object: {excerpt(line)}")
        t = row.get("t")
        if isinstance(t, bool) or not isinstance(t, (int, float)):
            raise FemError(f"{path}:{number}: no time 't' in this row; `plot` draws the rows "
                           f"`simulate --stats` writes")
        stats.rows.append(row)
        stats.line_numbers.append(number)
    if not stats.rows:
        raise FemError(f"{path}: is empty; `plot` draws the rows `simulate --stats` writes")
    return stats


def default_panels(files) -> dict:
    """{name: Panel}: every energy term the files have and their total, the volume ratio, the
    iterations and the residual; a panel none of the files has a key of is left out."""
    keys = list(dict.fromkeys(key for stats in files for row in stats.rows for key in row))
    energies = [key for key in keys if key.endswith("_energy") and not key.startswith("body_")]
    panels = {"energy": Panel("energy (J)", energies),
              "volume_ratio": Panel("volume / rest volume", ["volume_ratio"]),
              "iterations": Panel("iterations per step", ["newton_iters", "solver_iters"]),
              "residual": Panel("residual", ["residual"], "log")}
    return {name: panel for name, panel in panels.items() if set(panel.keys) & set(keys)}


def chosen_panels(files, quantities) -> dict:
    """{key: Panel} for --quantity: FemError for a key that a file does not have."""
    for stats in files:
        for key in quantities:
            if not stats.has(key):
                keys = list(dict.fromkeys(k for row in stats.rows for k in row))
                close = difflib.get_close_matches(key, keys, n=1)
                hint = f"did you mean {close[0]}?" if close else f"it has {', '.join(keys)}"
                raise FemError(f"--quantity {key}: not in {stats.path}; {hint}")
    return {key: Panel(key, [key], "log" if key == "residual" else "linear") for key in quantities}


def draw(files, panels, png: Path, numbers_file: Path, overwrite: bool):
    """Draw `panels` of every file into png, and write the numbers drawn into numbers_file."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(panels), 1, sharex=True, squeeze=False,
                             figsize=(WIDTH_IN, PANEL_HEIGHT_IN * len(panels)))
    for ax, panel in zip(axes[:, 0], panels.values()):
        draw_panel(ax, panel, files)
    axes[-1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    with atomic_open(png, "wb", overwrite=overwrite) as out:
        fig.savefig(out, format="png", dpi=DPI)
    plt.close(fig)
    numbers = {"x": "t (s)", "files": {stats.label: str(stats.path) for stats in files},
               "panels": {name: {"ylabel": panel.ylabel, "scale": panel.scale, "curves": panel.curves}
                          for name, panel in panels.items()}}
    with atomic_open(numbers_file, overwrite=overwrite) as out:
        json.dump(numbers, out, indent=1)


def draw_panel(ax, panel: Panel, files):
    """Every file's curves of the panel's keys on the matplotlib axes `ax`, kept in panel.curves.
    Each file has its line style; a key (a body) has one colour in every file, except in a panel
    of one curve a file, where the files have the colours."""
    drawn = [(f, stats, k, key, stats.column(key)) for f, stats in enumerate(files)
             for k, key in enumerate(panel.keys) if stats.has(key)]
    colour_by_file = all(len(curves) == 1 for *_, curves in drawn) and len(panel.keys) == 1
    for f, stats, k, key, curves in drawn:
        t = [to_float(row["t"]) for row in stats.rows]
        for body, y in enumerate(curves):
            several = len(curves) > 1
            ax.plot(t, y, color=f"C{f if colour_by_file else k + body}", label=f"{stats.label}: {key}"
                    + (f" (body {body})" if several else ""), linestyle=LINE_STYLES[f % len(LINE_STYLES)])
            panel.curves.append({"file": stats.label, "key": key, "body": body if several else None,
                                 "t": t, "y": [v if math.isfinite(v) else None for v in y]})
    ax.set_yscale(panel.scale)
    ax.set_ylabel(panel.ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


def label_files(files):
    """Each file's legend label: its name, or the path as given where two names are the same."""
    names = [stats.path.name for stats in files]
    for stats, name in zip(files, names):
        stats.label = name if names.count(name) == 1 else str(stats.path)


def run(args) -> int:
    """main.py plot: draw the stats files `args` names; returns the exit code."""
    png = Path(args.out)
    if png.suffix.lower() != ".png":
        raise FemError(f"--out {png}: the picture is a PNG; give a name ending in .png")
    numbers_file = png.with_suffix(".json")
    inputs = [Path(name) for name in args.stats]
    if any(path.resolve() == numbers_file.resolve() for path in inputs):
        raise FemError(f"--out {png}: its numbers would replace {numbers_file}, a stats file drawn; "
                       "give another --out")
    check_output(numbers_file, "--out", "file")
    refuse_overwrite(png, args.overwrite)
    refuse_overwrite(numbers_file, args.overwrite)
    files = [read_stats(path) for path in inputs]
    label_files(files)
    quantities = list(dict.fromkeys(args.quantity or []))
    panels = chosen_panels(files, quantities) if quantities else default_panels(files)
    if not panels:
        raise FemError(f"{inputs[0]}: none of energy, volume_ratio, newton_iters, residual in its rows; "
                       "name the keys to draw with --quantity")
    draw(files, panels, png, numbers_file, args.overwrite)
    print(f"wrote {png} ({', '.join(panels)} against t, {len(files)} file{'s' * (len(files) > 1)}) "
          f"and the numbers drawn, {numbers_file}")
    return 0
