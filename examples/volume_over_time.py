"""Load a scene, step it with linear and with corotational FEM, and plot each body's volume.

Works as a script and cell by cell in a notebook (from the repository's root, or anywhere
after `pip install .`):

    .venv/bin/python examples/volume_over_time.py cube86 --steps 100    # writes out/volume_cube86.png
"""

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # a clone without installing

import matplotlib
import matplotlib.pyplot as plt

import fem
from scenes import load_scene


def volume_history(scene, method, steps):
    """Times (s) and per-body volume ratios (steps + 1 lists) of one run."""
    sim = fem.Simulation(scene, method=method)
    times, volumes = [0.0], [sim.stats()["volume_ratio"]]
    for _ in range(steps):
        sim.step()
        stats = sim.stats()
        times.append(stats["t"])
        volumes.append(stats["volume_ratio"])
    return times, volumes


def plot(scene, runs, out):
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for method, (times, volumes), style in zip(runs, runs.values(), ("--", "-")):
        for b, body in enumerate(scene.bodies):
            ax.plot(times, [v[b] for v in volumes], style, label=f"{body.name}, {method}")
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("volume / rest volume")
    ax.set_title(f"{scene.name}: volume of each body, linear (dashed) and corotational FEM", fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", nargs="?", default="cube86")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--out", help="the plot's file (default out/volume_SCENE.png, beside the commands' "
                                          "other outputs, not in the current folder)")
    args = parser.parse_args()
    args.out = Path(args.out or f"out/volume_{Path(args.scene).stem}.png")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    matplotlib.use("Agg")
    fem.init("cpu", "f32")
    scene = load_scene(args.scene)
    runs = {method: volume_history(scene, method, args.steps) for method in ("linear", "corotational")}
    plot(scene, runs, args.out)
    for method, (_, volumes) in runs.items():
        print(f"{method}: volume ratio at the end " + ", ".join(f"{v:.3f}" for v in volumes[-1]))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
