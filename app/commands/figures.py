"""`main.py figures`: every figure in docs/, redrawn by the engine, each with the numbers it draws.

    python main.py figures --out out/figures                  # all of them: a few minutes on 2 cores
    python main.py figures --out docs --overwrite             # regenerate the committed ones
    python main.py figures --out out/f --only torsion_length  # some of them
    python main.py figures --out out/f --cggs ../shared/cggs  # also the coursework's own scenes

A figure NAME is two files: NAME.png and NAME.json, the numbers drawn in it (time series,
volume ratios at a frame, the benchmark's plotted points), so that a new run can be
compared with a committed one number by number.

    volume_SCENE          volume / rest volume of each body over time, linear vs corotational,
                          for every built-in scene
    torsion_length        the torsion bar's length along its axis and its largest distance from
                          the axis over time, linear vs corotational
    frame25_builtin       epcot and cube86 after 25 steps, linear vs corotational side by side,
                          coloured by volume ratio (like the coursework report's Figure 1)
    frame25_coursework    the same from the coursework's epcot- and cube86-scene.txt (--cggs)
    epcot_compare         epcot at t = 2 s, linear left and corotational right (the README's picture)
    epcot_compare_volume  the same, coloured by volume ratio
    accuracy_vs_time      the benchmark's plot, redrawn by `app.bench.plot` from docs/benchmark.json
                          (written by `main.py bench --docs`)
    hard_case_energy      total energy of a near-incompressible spinning cube at dt 0.5 s: the
                          one-solve step gains energy, the Newton step never does
    integrator_order      position error against dt of backward Euler, BDF2 and the trapezoidal
                          rule (app.bench.order)
    energy_drift          total energy over 10 s of a free spinning, twisting bar, each integrator

Every run takes the scene's own time step and solver settings (the Newton step), on the CPU
in f32 unless --arch or --precision say otherwise; pictures come from the software renderer,
whose pixels are the same on every run. A figure whose input is missing (the benchmark's
results, the coursework folder) is skipped with one line saying why, or is an error when
--only asks for it. docs/viewer.png is not made here: it is a screenshot of the window
(`main.py view epcot --compare`, then the `p` key).
"""

import difflib
import json
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
from PIL import Image

import fem
import scenes
from app import EXIT_INTERRUPTED, device, outputs, program_name
from app.bench import order
from app.bench import plot as bench_plot
from app.bench import report as bench_report
from app.commands.export import DIVIDER_COLOR, View
from app.files import atomic_open, refuse_overwrite
from app.render.overlay import volume_line
from fem.errors import FemError
from scenes.hard_cases import ENERGY_TOLERANCE, HARD_CASES, build_scene

DURATION_S = 4.0               # simulated time of the volume and length plots
QUICK_FRACTION = 0.25          # --quick: this part of every simulated time, to check the command
FRAME = 25                     # the coursework report's Figure 1 shows frame 25: 25 steps
STILL_TIME_S = 2.0             # epcot_compare: the README's picture
STILL_SIZE = (800, 400)        # pixels, both panels
PLOT_SIZE = (7.0, 3.6)         # inches, at PLOT_DPI
PLOT_DPI = 110
COURSEWORK_SCENES = ("epcot-scene.txt", "cube86-scene.txt")
# The hard case (scenes/hard_cases.py defines it once), at 25 times the scenes' dt: there the one-solve
# step gains energy, run alone in f32 or f64.
HARD_CASE, HARD_CASE_DT, HARD_CASE_S = "near-incompressible", 0.5, 10.0
STEP_KINDS = {"single": "one-solve step (single)", "newton": "Newton step (default)"}
METHODS = ("linear", "corotational")     # compared in the figures (not the naive teaching variant)
METHOD_STYLES = {"linear": "--", "corotational": "-"}
METHOD_COLOURS = {"linear": "C0", "corotational": "C1"}


# ---------------------------------------------------------------- what a figure is

@dataclass
class Drawn:
    """A figure made: save(file) writes its PNG; numbers are what it draws (JSON-ready)."""

    save: Callable
    numbers: dict


@dataclass
class Figure:
    """name: file stem; what: one line; draw(maker) -> Drawn; missing(maker): why it cannot
    be made here (None: it can)."""

    name: str
    what: str
    draw: Callable
    missing: Callable = lambda maker: None


def catalogue():
    """Every figure, in the order made: the one drawn from a file first (a bad file is found before
    any run), and figures that share a run after the first to need it."""
    figures = [Figure("accuracy_vs_time", "the benchmark's error against time, from its results", accuracy_plot,
                      benchmark_missing)]
    figures += [Figure(f"volume_{name}", f"{name}: volume over time, linear vs corotational",
                       lambda maker, name=name: volume_plot(maker, name))
                for name in scenes.builtin_scenes()]
    return figures + [
        Figure("torsion_length", "torsion: the bar's length and thickness over time, linear vs corotational",
               torsion_length),
        Figure("frame25_builtin", f"epcot and cube86 at frame {FRAME}, built-in scenes",
               lambda maker: frame_grid(maker, ["epcot", "cube86"], "built-in scene")),
        Figure("frame25_coursework", f"epcot and cube86 at frame {FRAME}, the coursework's scene files",
               lambda maker: frame_grid(maker, [maker.cggs / f for f in COURSEWORK_SCENES], "coursework"),
               lambda maker: None if maker.cggs else "needs --cggs FOLDER (the coursework's *-scene.txt files)"),
        Figure("epcot_compare", f"epcot at t = {STILL_TIME_S:g} s, linear vs corotational",
               lambda maker: epcot_still(maker, "body")),
        Figure("epcot_compare_volume", f"epcot at t = {STILL_TIME_S:g} s, coloured by volume ratio",
               lambda maker: epcot_still(maker, "volume")),
        Figure("hard_case_energy", f"the {HARD_CASE} cube at dt {HARD_CASE_DT:g} s: one-solve vs Newton step",
               hard_case_energy),
        Figure("integrator_order", "error against dt, backward Euler (first order) against BDF2 and the "
               "trapezoidal rule (second)",
               lambda maker: Drawn(*order.order_figure(PLOT_SIZE, PLOT_DPI))),
        Figure("energy_drift", f"energy over {order.DRIFT_SECONDS:g} s of a free spinning, twisting bar, "
               "each integrator", lambda maker: Drawn(*order.drift_figure(PLOT_SIZE, PLOT_DPI, maker.steps(order.DRIFT_SECONDS, order.DRIFT_DT)
                                                        * order.DRIFT_DT))),
    ]


def benchmark_missing(maker):
    """Why accuracy_vs_time cannot be drawn (no benchmark results), or None. An installed package
    has no docs/ to read them from or write them into: it measures its own into a folder."""
    if maker.bench.is_file():
        return None
    if bench_report.DOCS.is_dir():
        return f"{maker.bench} not found (`{program_name()} bench --docs` writes it, in about 25 minutes)"
    return (f"{maker.bench} not found: an installed package has no docs/ folder; `{program_name()} bench "
            f"--out DIR` measures the results (about 25 minutes), then `figures --bench DIR/results.json`")


class Maker:
    """What the figures share: options, and runs made once for every figure that needs them.

    quick: shorten every simulated time (QUICK_FRACTION); cggs: the coursework folder or None;
    bench: the benchmark's results.json to redraw.
    """

    def __init__(self, quick: bool, cggs: Path | None, bench_results: Path):
        self.quick, self.cggs, self.bench = quick, cggs, bench_results
        self.histories = {}        # (scene, method, seconds) -> History
        self.compare_runs = {}     # scene -> CompareRun

    def steps(self, seconds, dt):
        """Steps of dt (s) that make `seconds` of simulated time, a quarter of them when quick."""
        return round(seconds * (QUICK_FRACTION if self.quick else 1) / dt)

    def history(self, name, method, seconds):
        key = (name, method, seconds)
        if key not in self.histories:
            scene = scenes.load_scene(name)
            sim = fem.Simulation(scene, method=method)
            self.histories[key] = record(sim, self.steps(seconds, scene.solver.dt))
        return self.histories[key]

    def compare_run(self, ref):
        if ref not in self.compare_runs:
            self.compare_runs[ref] = CompareRun(scenes.load_scene(ref))
        return self.compare_runs[ref]


# ---------------------------------------------------------------- runs

@dataclass
class History:
    """One run sampled at t = 0 and after every step: time (s), each body's volume / rest
    volume, total energy (J) and positions ((n, 3) m)."""

    t: list = field(default_factory=list)
    volume_ratio: list = field(default_factory=list)
    total_energy: list = field(default_factory=list)
    positions: list = field(default_factory=list)


def record(sim, steps) -> History:
    """Step sim `steps` times, sampling before the first step and after every step."""
    history = History()
    for k in range(steps + 1):
        if k:
            sim.step()
        stats = sim.stats()
        history.t.append(sim.t)
        history.volume_ratio.append(stats["volume_ratio"])
        history.total_energy.append(stats["total_energy"])
        history.positions.append(sim.positions())
    return history


class CompareRun:
    """A scene side by side in one Simulation (linear left, corotational right, as `export
    --compare` shows it), pictured with both colourings as it runs forward."""

    def __init__(self, scene):
        self.scene, self.dt, self.steps = scene, scene.solver.dt, 0
        self.sim = fem.Simulation(scene.side_by_side())
        self.views = {color: View(self.sim, scene, True, color, "software", *STILL_SIZE)
                      for color in ("body", "volume")}

    def pictures(self, steps, extra_lines=()):
        """{colour: picture (H, W, 3) uint8} after `steps` steps, and the numbers they show.
        Every view draws every time, so that both cameras back off alike."""
        if steps < self.steps:
            raise ValueError(f"{self.scene.name}: already {self.steps} steps, cannot show step {steps}")
        for _ in range(steps - self.steps):
            self.sim.step()
        self.steps = steps
        ratios = self.sim.stats()["volume_ratio"]
        names = [body.name for body in self.scene.bodies]
        volumes = {"linear": dict(zip(names, ratios[:len(names)])),
                   "corotational": dict(zip(names, ratios[len(names):]))}
        bodies = [(name, method, ratio) for method, by_body in volumes.items() for name, ratio in by_body.items()]
        lines = [f"t = {self.sim.t:.2f} s", *extra_lines, volume_line(bodies)]     # as the export says it
        pictures = {color: view.annotated(view.picture(self.sim), view.caption + lines)
                    for color, view in self.views.items()}
        numbers = {"scene": self.scene.name, "steps": steps, "dt": self.dt, "t": self.sim.t,
                   "volume_ratio": volumes}
        return pictures, numbers


# ---------------------------------------------------------------- the figures

def volume_plot(maker, name):
    scene = scenes.load_scene(name)
    runs = {method: maker.history(name, method, DURATION_S) for method in METHODS}
    fig, ax = new_plot()
    for b, body in enumerate(scene.bodies):
        for method, run in runs.items():
            ratios = [r[b] for r in run.volume_ratio]
            ax.plot(run.t, ratios, METHOD_STYLES[method], color=f"C{b}",
                    label=f"{body.name}, {method} (ends at {ratios[-1]:.3f})")
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("volume / rest volume")
    ax.set_title(f"{name}: volume of each body, linear (dashed) and corotational (solid) FEM\n"
                 f"dt {scene.solver.dt:g} s, {scene.solver.step} step, {tet_count(scene)} tets", fontsize=9)
    ax.legend(fontsize=7)
    names = [body.name for body in scene.bodies]
    numbers = {"scene": name, "dt": scene.solver.dt, "t": runs["linear"].t,
               "volume_ratio": {method: {n: [r[b] for r in run.volume_ratio] for b, n in enumerate(names)}
                                for method, run in runs.items()}}
    return Drawn(plot_saver(fig), numbers)


def torsion_length(maker):
    """The bar's length along its long axis and its largest distance from that axis (the axis
    through its centre of vertices): whether linear FEM grows it along or across the axis."""
    scene = scenes.load_scene("torsion")
    rest = scene.bodies[0].mesh.vertices
    axis = int(np.argmax(np.ptp(rest, axis=0)))     # the bar's long axis
    name = "xyz"[axis]
    runs = {method: maker.history("torsion", method, DURATION_S) for method in METHODS}
    lengths = {method: [bar_length(x, axis) for x in run.positions] for method, run in runs.items()}
    radii = {method: [bar_radius(x, axis) for x in run.positions] for method, run in runs.items()}
    fig, (left, right) = new_plot(columns=2)
    for ax, values, rest_value, what in ((left, lengths, bar_length(rest, axis), f"length along {name} (m)"),
                                         (right, radii, bar_radius(rest, axis), "largest distance from the axis (m)")):
        for method, series in values.items():
            ax.plot(runs[method].t, series, METHOD_STYLES[method], color=METHOD_COLOURS[method],
                    label=f"{method}: {min(series):.3f} to {max(series):.3f} m")
        ax.axhline(rest_value, color="grey", lw=0.8, label=f"at rest: {rest_value:.3f} m")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(what)
        ax.legend(fontsize=7)
    left.set_title(f"along the axis: the bar's extent in {name}", fontsize=9)
    right.set_title("across the axis: how far its farthest vertex is from it", fontsize=9)
    fig.suptitle(f"torsion: a {np.ptp(rest[:, axis]):g} m bar twisted about its long axis {name}, linear (dashed) "
                 f"vs corotational (solid); dt {scene.solver.dt:g} s, {scene.solver.step} step", fontsize=9)
    numbers = {"scene": "torsion", "axis": name, "rest_length": bar_length(rest, axis),
               "rest_radius": bar_radius(rest, axis), "t": runs["linear"].t, "length": lengths, "radius": radii}
    return Drawn(plot_saver(fig), numbers)


def bar_length(positions, axis):
    """The extent (m) of positions (n, 3) along axis 0, 1 or 2."""
    return float(np.ptp(positions[:, axis]))


def bar_radius(positions, axis):
    """The largest distance (m) of positions (n, 3) from the line along `axis` through their mean."""
    across = np.delete(positions - positions.mean(axis=0), axis, axis=1)
    return float(np.linalg.norm(across, axis=1).max())


def frame_grid(maker, refs, source):
    """Each scene after FRAME steps, linear vs corotational, coloured by volume ratio, one above another."""
    rows, numbers = [], []
    for ref in refs:
        run = maker.compare_run(ref)
        lines = [f"frame {FRAME}: {FRAME} steps of {run.dt:g} s", f"{source} {Path(ref).name}"]
        pictures, shown = run.pictures(FRAME, lines)
        rows.append(pictures["volume"])
        numbers.append({"source": str(ref), **shown})
    divider = np.full((2, rows[0].shape[1], 3), DIVIDER_COLOR, np.uint8)
    image = np.concatenate([part for row in rows for part in (row, divider)][:-1])
    return Drawn(image_saver(image), {"frame": FRAME, "scenes": numbers})


def epcot_still(maker, color):
    run = maker.compare_run("epcot")
    pictures, numbers = run.pictures(round(STILL_TIME_S / run.dt))
    return Drawn(image_saver(pictures[color]), numbers)


def accuracy_plot(maker):
    try:
        results = json.loads(maker.bench.read_text())
        plotted = bench_plot.numbers(results, maker.bench)
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise FemError(f"{maker.bench}: not the results of `main.py bench` ({error})") from None
    return Drawn(lambda file: bench_plot.plot(results, file), plotted)


def hard_case_energy(maker):
    case = replace(next(c for c in HARD_CASES if c.name == HARD_CASE), dt=HARD_CASE_DT)
    scene, _ = build_scene([case], ["corotational"])
    steps = maker.steps(HARD_CASE_S, HARD_CASE_DT)
    runs = {step: record(fem.Simulation(scene, step=step), steps) for step in STEP_KINDS}
    tolerance = ENERGY_TOLERANCE[fem.runtime.current()["precision"]]   # round-off, as the tests allow
    fig, ax = new_plot()
    rises = {}
    for (step, label), colour in zip(STEP_KINDS.items(), ("C3", "C0")):
        energy = runs[step].total_energy
        rises[step] = max(np.diff(energy)) / energy[0]
        growth = (f"rises to {max(energy) / energy[0]:.3g} times its start" if rises[step] > tolerance
                  else "never rises")
        ax.plot(runs[step].t, energy, "-o", ms=2.5, color=colour, label=f"{label}: {growth}")
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("total energy (J): kinetic + elastic")
    ax.set_title(f"hard case '{HARD_CASE}': {case.what}\ncorotational, damped, at a large time step "
                 f"dt = {HARD_CASE_DT:g} s: the energy should only fall", fontsize=9)
    ax.legend(fontsize=7)
    numbers = {"case": HARD_CASE, "what": case.what, "dt": HARD_CASE_DT, "t": runs["newton"].t,
               "total_energy": {step: run.total_energy for step, run in runs.items()},
               "largest_rise_over_start": rises}
    return Drawn(plot_saver(fig), numbers)


# ---------------------------------------------------------------- drawing and saving

def new_plot(columns=1):
    """A matplotlib figure for the docs: (figure, axes), one axes per column."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    width, height = PLOT_SIZE
    return plt.subplots(1, columns, figsize=(width * (1 + 0.5 * (columns - 1)), height))


def plot_saver(fig):
    def save(file):
        import matplotlib.pyplot as plt
        fig.tight_layout()
        fig.savefig(file, format="png", dpi=PLOT_DPI)
        plt.close(fig)
    return save


def image_saver(image):
    return lambda file: Image.fromarray(image).save(file, format="PNG")


def tet_count(scene):
    return sum(len(body.mesh.tets) for body in scene.bodies)


def write(out: Path, name: str, drawn: Drawn):
    """out/name.png and out/name.json, each under a temporary name until complete."""
    with atomic_open(out / f"{name}.png", "wb") as f:
        drawn.save(f)
    with atomic_open(out / f"{name}.json") as f:
        json.dump(drawn.numbers, f, indent=1)


# ---------------------------------------------------------------- command

def chosen(figures, only, maker):
    """(figures to make, [(name, why skipped)]): --only's, each of which must be possible, or
    every figure that can be made here."""
    names = [f.name for f in figures]
    for name in only or []:
        if name not in names:
            hint = difflib.get_close_matches(name, names, n=1)
            also = f"did you mean {hint[0]!r}?" if hint else f"figures: {', '.join(names)}"
            raise FemError(f"--only {name}: no such figure ({also})")
    figures = [f for f in figures if not only or f.name in only]
    missing = {f.name: f.missing(maker) for f in figures}
    for name, why in missing.items():
        if why and only:
            raise FemError(f"--only {name}: {why}")
    return [f for f in figures if not missing[f.name]], [(n, why) for n, why in missing.items() if why]


def check_cggs(cggs):
    """The coursework folder as a Path, FemError unless it holds the scenes frame25_coursework needs."""
    if cggs is None:
        return None
    folder = Path(cggs)
    if not folder.is_dir():
        raise FemError(f"--cggs {folder}: no such folder")
    absent = [name for name in COURSEWORK_SCENES if not (folder / name).is_file()]
    if absent:
        raise FemError(f"--cggs {folder}: no {' or '.join(absent)} in it")
    return folder


def run(args) -> int:
    """main.py figures: make the figures the parsed command line `args` asks for; returns the exit code."""
    out = Path(args.out)
    bench_results = Path(args.bench) if args.bench else bench_report.DOCS / bench_report.DOCS_FILES["json"]
    if args.bench and not bench_results.is_file():
        raise FemError(f"--bench {bench_results}: no such file")
    maker = Maker(args.quick, check_cggs(args.cggs), bench_results)
    figures, skipped = chosen(catalogue(), args.only, maker)
    refuse_overwrite(out, args.overwrite)
    outputs.remove_stale_temporaries(out)          # what a killed run left
    device.start(args)

    began, written = time.perf_counter(), []
    for name, why in skipped:
        print(f"skipped {name}: {why}", file=sys.stderr)
    try:
        for i, figure in enumerate(figures, 1):
            print(f"[{i}/{len(figures)}] {figure.name}: {figure.what}", file=sys.stderr, flush=True)
            start = time.perf_counter()
            write(out, figure.name, figure.draw(maker))
            written.append((figure.name, time.perf_counter() - start))
    except KeyboardInterrupt:
        kept = ", ".join(name for name, _ in written) or "none"
        print(f"interrupted: kept the complete figures ({kept}) in {out}", file=sys.stderr)
        return EXIT_INTERRUPTED
    minutes = (time.perf_counter() - began) / 60
    print(f"wrote {len(written)} figures into {out} ({minutes:.1f} min), each NAME.png with its numbers "
          "in NAME.json:")
    for name, seconds in written:
        print(f"  {name}.png  {name}.json  ({seconds:.0f} s)")
    return 0
