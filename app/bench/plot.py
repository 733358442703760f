"""The benchmark's plot: error against wall time per simulated second, one panel per scene
(`main.py figures` redraws it from docs/benchmark.json)."""

from app.bench import direct
from app.bench.conclusions import final_error
from app.bench.plan import (BASELINE_TOLERANCE, DT_FACTORS, ERROR_GOAL, JACOBI_ITERATIONS, PCG_TOLERANCES,
                            integrator_of, sci, step_name)

COLOURS = {   # (method, step, integrator)
    ("corotational", "newton", "backward-euler"): "tab:blue", ("corotational", "newton", "bdf2"): "tab:cyan",
    ("corotational", "single", "backward-euler"): "tab:purple", ("corotational", "single", "bdf2"): "tab:pink",
    ("linear", "newton", "backward-euler"): "tab:orange", ("linear", "newton", "bdf2"): "tab:brown",
    ("linear", "single", "backward-euler"): "tab:orange",
    ("corotational", "newton", "trapezoidal"): "tab:green", ("corotational", "single", "trapezoidal"): "tab:olive"}
MARKERS = {"backward-euler": "o-", "bdf2": "v-", "trapezoidal": "P-"}   # the dt axis of each integrator
LEGEND_INCHES = 1.2   # below the plots
DPI = 110
# Where a point's label may go, in points from the point, nearest first: beside it at each corner, then
# further out. A label that fits nowhere inside its panel without covering another label or a point is
# left out: several series share each dt and each tolerance, so the dt labels repeat from line to line.
LABEL_OFFSETS = [(dx * d, dy * d) for d in (3, 8, 14) for dx, dy in ((1, 1), (1, -1), (-1, 1), (-1, -1))] \
    + [(0, 14), (0, -14), (0, 22), (0, -22)]
MARKER_POINTS = 3.0   # half the side of the box around a point that no label may cover (5 pt markers)


def series(scene):
    """{(legend, colour, style): [(s per sim s, error, point label)]}: the lines of one scene's plot."""
    out = {}

    def add(row, what, style, label):
        error = final_error(row)
        if error is None:
            return
        integrator = integrator_of(row)
        kind = "linear" if row["method"] == "linear" else f"corotational {step_name(row)}"
        kind += {"bdf2": ", BDF2", "trapezoidal": ", trapezoidal"}.get(integrator, "")   # unmarked: backward Euler
        key = (f"{kind}, {what}", COLOURS[row["method"], row["step"], integrator], style)
        out.setdefault(key, []).append((row["s_per_sim_s"], max(error, 1e-12), label))

    dts = "dt " + " / ".join(format(f * scene["dt"], "g") for f in DT_FACTORS) + " s"
    tolerances = "PCG " + " / ".join(map(sci, PCG_TOLERANCES))
    jacobi = "Jacobi x" + " / ".join(map(str, JACOBI_ITERATIONS))
    ends = (PCG_TOLERANCES[0], PCG_TOLERANCES[-1], JACOBI_ITERATIONS[0], JACOBI_ITERATIONS[-1])
    for r in scene["variants"]:   # only the ends of the tolerance and Jacobi axes are labelled: they crowd
        integrator = integrator_of(r)
        if r["solver"] == "pcg" and r["tolerance"] == BASELINE_TOLERANCE:
            add(r, dts, MARKERS[integrator], f"{r['dt']:g} s")
        if r["solver"] == "pcg" and r["dt_factor"] == 1 and integrator == "backward-euler":
            add(r, tolerances, "^--", sci(r["tolerance"]) if r["tolerance"] in ends else "")
        if r["solver"] == "jacobi":
            add(r, jacobi, "s:", f"J{r['iterations']}" if r["iterations"] in ends else "")
        if r["solver"] == "direct":   # results from before the baseline had backends have no "backend"
            add(r, "direct", "D", direct.BACKENDS[r["backend"]].label if "backend" in r else "")
    return out


def numbers(results, source):
    """What the plot draws, as `figures` writes it beside the PNG (accuracy_vs_time.json)."""
    series_of = {s["name"]: {legend: points for (legend, _, _), points in series(s).items()} for s in results["scenes"]}
    return {"source": str(source), "x": "wall s per simulated s", "y": "position error", "series": series_of}


def plot(results, file):
    """Draw the benchmark's figure into `file` as a PNG."""
    fig = figure(results)
    fig.savefig(file, format="png", dpi=DPI)
    import matplotlib.pyplot as plt
    plt.close(fig)


def figure(results):
    """The figure, laid out and with its point labels placed (a matplotlib Figure)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    scenes = results["scenes"]
    cols = min(3, len(scenes))
    rows = -(-len(scenes) // cols)
    height = 4.6 * rows + LEGEND_INCHES
    fig, axes = plt.subplots(rows, cols, figsize=(max(6 * cols, 11), height), squeeze=False, dpi=DPI)
    labels = {}
    for ax, s in zip(axes.ravel(), scenes):
        lowest, highest = min(s["reference_floor"], ERROR_GOAL), ERROR_GOAL
        labels[ax] = []
        for (legend, colour, style), points in series(s).items():
            xs, ys, _ = zip(*points)
            lowest, highest = min(lowest, *ys), max(highest, *ys)
            ax.plot(xs, ys, style, color=colour, alpha=0.85, ms=5, label=legend)
            labels[ax] += [(x, y, label, colour, i in (0, len(points) - 1)) for i, (x, y, label) in enumerate(points)]
        ax.axhline(ERROR_GOAL, color="green", lw=1, ls=":", label=f"the goal: {100 * ERROR_GOAL:g} % of the scene size")
        ax.axhspan(1e-12, s["reference_floor"], color="grey", alpha=0.15, lw=0,
                   label="below the reference's own error (estimate)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1, 2, 5)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(lowest / 3, highest * 3)        # room for the labels of the lowest and highest points
        ax.set_title(f"{s['name']} ({s['tets']} tets, scene dt {s['dt']:g} s, dt_ref {s['reference_dt']:g} s)",
                     fontsize=9)
        ax.set_xlabel("wall time per simulated second (s)")
        ax.set_ylabel(f"position error at t = {s['checkpoints'][-1]:g} s")
        ax.grid(True, which="major", alpha=0.3)
    for ax in axes.ravel()[len(scenes):]:
        ax.axis("off")
    handles, names = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=3, fontsize=8, frameon=False)
    m = results["machine"]
    fig.suptitle("Position error (RMS distance to the reference / bounding-box diagonal) against wall time per "
                 f"simulated second; {m['backend']} {m['precision']}, {m['cores']} cores\n"
                 "points: dt, PCG tolerance, Jacobi iterations; backward Euler unless marked BDF2 or trapezoidal "
                 "(log-log: down and left is better)", fontsize=9)
    fig.tight_layout(rect=(0, LEGEND_INCHES / height, 1, 1))
    for ax, points in labels.items():     # after the layout: the labels are placed where they will be drawn
        place_labels(ax, points)
    return fig


def place_labels(ax, labels):
    """Write each (x, y, text, colour, first) of labels beside its point, at the first of LABEL_OFFSETS
    where it stays inside the panel and covers no point and no label placed before it; the `first`
    ones (a line's ends) are placed before the rest, and a label with no room is left out.
    Returns the labels written (matplotlib Annotations)."""
    ax.get_xlim(), ax.get_ylim()          # the limits now final: positions below are the drawn ones
    renderer = ax.figure.canvas.get_renderer()
    pixels = ax.figure.dpi / 72.0
    panel = ax.get_window_extent(renderer)
    taken = [box_around(ax.transData.transform((x, y)), MARKER_POINTS * pixels) for x, y, *_ in labels]
    written = []
    for x, y, text, colour, _ in sorted(labels, key=lambda label: not label[4]):
        if not text:
            continue
        note = ax.annotate(text, (x, y), fontsize=6, color=colour, textcoords="offset points", xytext=(0, 0))
        for dx, dy in LABEL_OFFSETS:
            note.xyann = (dx, dy)
            note.set_horizontalalignment("left" if dx > 0 else "right" if dx < 0 else "center")
            note.set_verticalalignment("bottom" if dy > 0 else "top" if dy < 0 else "center")
            box = note.get_window_extent(renderer)
            if inside(box, panel) and not any(overlap(box, other) for other in taken):
                taken.append(box)
                written.append(note)
                break
        else:
            note.remove()
    return written


def box_around(centre, half):
    from matplotlib.transforms import Bbox
    return Bbox.from_extents(centre[0] - half, centre[1] - half, centre[0] + half, centre[1] + half)


def inside(box, panel):
    return panel.x0 <= box.x0 and box.x1 <= panel.x1 and panel.y0 <= box.y0 and box.y1 <= panel.y1


def overlap(a, b):
    """Whether two boxes share more than an edge."""
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1
