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
# A point label's room, in points (6 pt text): labels closer than this are stacked upwards, as
# the points of several series at one dt, or one tolerance, fall on top of each other.
LABEL_WIDTH, LABEL_HEIGHT = 24.0, 7.0


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
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    scenes = results["scenes"]
    cols = min(3, len(scenes))
    rows = -(-len(scenes) // cols)
    height = 4.6 * rows + LEGEND_INCHES
    fig, axes = plt.subplots(rows, cols, figsize=(max(6 * cols, 11), height), squeeze=False)
    for ax, s in zip(axes.ravel(), scenes):
        lowest = min(s["reference_floor"], ERROR_GOAL)
        labels = []
        for (legend, colour, style), points in series(s).items():
            xs, ys, _ = zip(*points)
            lowest = min(lowest, *ys)
            ax.plot(xs, ys, style, color=colour, alpha=0.85, ms=5, label=legend)
            labels += [(x, y, label, colour) for x, y, label in points]
        ax.axhline(ERROR_GOAL, color="green", lw=1, ls=":", label=f"the goal: {100 * ERROR_GOAL:g} % of the scene size")
        ax.axhspan(1e-12, s["reference_floor"], color="grey", alpha=0.15, lw=0,
                   label="below the reference's own error (estimate)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1, 2, 5)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_ylim(bottom=lowest / 3)
        ax.set_title(f"{s['name']} ({s['tets']} tets, scene dt {s['dt']:g} s, dt_ref {s['reference_dt']:g} s)",
                     fontsize=9)
        ax.set_xlabel("wall time per simulated second (s)")
        ax.set_ylabel(f"position error at t = {s['checkpoints'][-1]:g} s")
        ax.grid(True, which="major", alpha=0.3)
        place_labels(ax, labels)
    for ax in axes.ravel()[len(scenes):]:
        ax.axis("off")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    m = results["machine"]
    fig.suptitle("Position error (RMS distance to the reference / bounding-box diagonal) against wall time per "
                 f"simulated second; {m['backend']} {m['precision']}, {m['cores']} cores\n"
                 "points: dt, PCG tolerance, Jacobi iterations; backward Euler unless marked BDF2 or trapezoidal "
                 "(log-log: down and left is better)", fontsize=9)
    fig.tight_layout(rect=(0, LEGEND_INCHES / height, 1, 1))
    fig.savefig(file, format="png", dpi=110)
    plt.close(fig)


def place_labels(ax, labels):
    """Write each (x, y, text, colour) of labels beside its point, lifted above the labels
    already placed where it would overlap them; returns the offsets used, in points."""
    ax.get_xlim(), ax.get_ylim()          # the limits now final: positions below are the drawn ones
    to_points = 72.0 / ax.figure.dpi
    placed, offsets = [], []
    for x, y, text, colour in labels:
        if not text:
            continue
        px, py = ax.transData.transform((x, y)) * to_points
        lift = 0.0
        while any(abs(px - qx) < LABEL_WIDTH and abs(py + lift - qy) < LABEL_HEIGHT for qx, qy in placed):
            lift += LABEL_HEIGHT
        placed.append((px, py + lift))
        offsets.append((3.0, 3.0 + lift))
        ax.annotate(text, (x, y), fontsize=6, color=colour, textcoords="offset points", xytext=offsets[-1])
    return offsets
