"""softfem command line: simulate, export, view, bench, scenes.

    python main.py                        # the window (or, without a display, export the default scene)
    python main.py simulate cube86 --steps 50 --stats s.jsonl
    python main.py export epcot --compare --frames 150 --out out/epcot --video out/epcot.mp4
    python main.py view bunny
    python main.py bench --quick --out b
    python main.py scenes

Bad input ends with one line `error: ...` on stderr and exit code 2 (a traceback
only with --debug).
"""

import argparse
import math
import os
import sys
from pathlib import Path

DEFAULT_SCENE = "epcot"


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage mistake as one `error:` line and exit code 2."""

    def error(self, message):
        print(f"error: {self.prog}: {message} (see --help)", file=sys.stderr)
        sys.exit(2)


def number(kind, low, inclusive=False):
    """An argparse type: a finite `kind` (int or float) > low (>= low when inclusive)."""
    def convert(text):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                             f"got {text!r}") from None
        if not math.isfinite(value) or not (value >= low if inclusive else value > low):
            raise argparse.ArgumentTypeError(f"must be {'>=' if inclusive else '>'} {low}, got {text}")
        return value
    return convert


POSITIVE = number(float, 0)
COUNT = number(int, 1, inclusive=True)
STEPS = number(int, 0, inclusive=True)


def add_common(p):
    """Options every command that runs the engine shares."""
    p.add_argument("--arch", default="cpu", choices=["cpu", "gpu", "auto"],
                   help="Taichi backend; auto picks CUDA when present, else the CPU (default cpu)")
    p.add_argument("--precision", default="f32", choices=["f32", "f64"], help="float type (default f32)")
    p.add_argument("--debug", action="store_true", help="show tracebacks and enable Taichi's checks")


def add_scene_options(p, scene_required=True):
    """The scene and what may override it."""
    if scene_required:
        p.add_argument("scene", help="built-in name (see `scenes`), a .toml file or a coursework *-scene.txt")
    else:
        p.add_argument("scene", nargs="?", default=DEFAULT_SCENE,
                       help=f"built-in name, .toml or coursework *-scene.txt (default {DEFAULT_SCENE})")
    m = p.add_mutually_exclusive_group()
    m.add_argument("--linear", dest="method", action="store_const", const="linear",
                   help="every body uses linear FEM")
    m.add_argument("--corotational", dest="method", action="store_const", const="corotational",
                   help="every body uses corotational FEM")
    p.add_argument("--solver", choices=["pcg", "jacobi"], help="linear solver (scene default: pcg)")
    p.add_argument("--tol", type=POSITIVE, help="relative residual tolerance of the solve")
    p.add_argument("--max-iters", type=COUNT, help="iteration cap of the solve")
    p.add_argument("--dt", type=POSITIVE, help="time step, s")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a TOML scene value, e.g. --set body.soft.mesh.cells=[8,8,8]")
    add_common(p)


def build_parser():
    parser = Parser(prog="main.py", description="Linear and corotational soft bodies (tet FEM, Taichi).")
    parser.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    sub = parser.add_subparsers(dest="command", parser_class=Parser)

    p = sub.add_parser("simulate", help="run a scene without a window and summarise it")
    add_scene_options(p)
    p.add_argument("--steps", type=STEPS, default=100, help="number of steps (default 100)")
    p.add_argument("--stats", metavar="FILE.jsonl", help="one JSON object per step ('-' for stdout)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing stats file")

    sub.add_parser("scenes", help="list the built-in scenes")

    p = sub.add_parser("export", help="render frames (PNG) and a video without a display")
    add_scene_options(p, scene_required=False)
    p.add_argument("--frames", type=COUNT, default=120, help="number of frames (default 120)")
    p.add_argument("--out", default="out", help="folder for the PNG frames (default out)")
    p.add_argument("--video", metavar="FILE", help="also write a .mp4 (H.264) or .gif")
    p.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    p.add_argument("--fps", type=POSITIVE, default=30, help="video frame rate (default 30)")
    p.add_argument("--steps-per-frame", type=COUNT, help="simulation steps per frame (default: real time at --fps)")
    p.add_argument("--compare", action="store_true", help="left copy linear, right copy corotational")
    p.add_argument("--color", default="body", choices=["body", "volume", "strain"], help="colour mode")
    p.add_argument("--renderer", default="auto", choices=["auto", "ggui", "software"],
                   help="GGUI offscreen (needs Vulkan) or the built-in software renderer")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty folder / replace the video")

    p = sub.add_parser("view", help="interactive window: click to push, c toggles corotation")
    add_scene_options(p, scene_required=False)
    p.add_argument("--compare", action="store_true", help="left copy linear, right copy corotational")
    p.add_argument("--stats", metavar="FILE.jsonl", help="one JSON object per rendered frame, with events")
    p.add_argument("--size", default="1280x720", help="window size WxH (default 1280x720)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing stats file")

    p = sub.add_parser("bench", help="what accuracy costs in time: tables and a plot")
    p.add_argument("--quick", action="store_true", help="fewer scenes and steps (under 3 minutes)")
    p.add_argument("--out", default="bench", help="output folder (default bench)")
    p.add_argument("--scenes", nargs="+", help="scenes to measure (default: all seed scenes and boxes)")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty folder")
    add_common(p)
    return parser


def has_display():
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def dispatch(args):
    import fem

    if args.command == "scenes":
        for name, description in fem.builtin_scenes().items():
            print(f"{name:10s} {description}")
        return 0
    if args.command == "simulate":
        from app import simulate
        return simulate.run(args)
    if args.command == "export":
        from app import export
        return export.run(args)
    if args.command == "view":
        from app import viewer
        return viewer.run(args)
    if args.command == "bench":
        from app import bench
        return bench.run(args)
    raise AssertionError(args.command)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    if not [a for a in argv if not a.startswith("-")]:
        # no subcommand: the window when there is a display, else a useful export
        if has_display():
            argv = ["view"] + argv
        else:
            # into a folder of its own (out/epcot, out/epcot-2, ...): earlier output is never touched
            out, copy = Path("out") / DEFAULT_SCENE, 1
            while out.exists() and (not out.is_dir() or any(out.iterdir())):
                copy += 1
                out = Path("out") / f"{DEFAULT_SCENE}-{copy}"
            print(f"no display: exporting {DEFAULT_SCENE} (linear vs corotational) to {out}/",
                  file=sys.stderr)
            argv = ["export", DEFAULT_SCENE, "--compare", "--frames", "150", "--out", str(out),
                    "--video", str(out / f"{DEFAULT_SCENE}.mp4")] + argv
    args = parser.parse_args(argv)
    from fem.errors import FemError

    try:
        return dispatch(args)
    except FemError as e:
        if args.debug:
            raise
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
