"""softfem's command line: `python main.py COMMAND ...`, or `softfem COMMAND ...` once installed.

    python main.py                        # the window (or, without a display, export the default scene)
    python main.py help                   # the commands; `help COMMAND` for one of them
    python main.py simulate cube86 --steps 50 --stats s.jsonl && python main.py plot s.jsonl
    python main.py export epcot --compare --frames 150 --out out/epcot-compare --video out/epcot-compare.mp4

Bad input ends with one line `error: ...` on stderr and exit code 2, before any work starts
where it can be found out then (a traceback only with --debug). Exit codes: 0 done, 1 the run
failed (every step rejected), 2 bad input, 130 interrupted (Ctrl-C, SIGTERM, SIGHUP, SIGQUIT,
SIGUSR1/2, SIGALRM, SIGXCPU; complete files and rows are kept).
"""

import argparse
import contextlib
import difflib
import errno
import importlib
import math
import os
import re
import sys
from pathlib import Path

from app import EXIT_BAD_INPUT, EXIT_BROKEN_PIPE, EXIT_INTERRUPTED, program_name
from app import outputs
from app.display import display_problem
from app.files import check_output, interrupt_on_sigterm
from fem.errors import FemError, SizeLimitError, one_line
from fem.scene import INTEGRATOR_CHOICES

DEFAULT_SCENE = "epcot"
DEFAULT_FRAMES = 150            # of the export a bare `main.py` makes without a display
# What each command writes, as (attribute, option, "file" | "folder"): checked before any work.
OUTPUTS = {
    "simulate": [("stats", "--stats", "file")],
    "export": [("out", "--out", "folder"), ("video", "--video", "file")],
    "view": [("stats", "--stats", "file"), ("out", "--out", "folder")],
    "bench": [("out", "--out", "folder")],
    "figures": [("out", "--out", "folder")],
    "plot": [("out", "--out", "file")],
}
EPILOG = """\
examples:
  {prog}                                     the window; without a display, export the default scene
  {prog} simulate my_shape.obj --steps 200   your own mesh (OBJ/STL/PLY/OFF surface, .mesh/.msh/.vtk tets)
  {prog} export epcot --compare --frames 60  linear vs corotational as PNG frames in out/epcot-N
  {prog} plot a.jsonl b.jsonl --out ab.png   draw simulate's --stats files over each other
  {prog} help export                         every option of one command

SCENE is a built-in name (see `scenes`), a .toml scene file, a coursework *-scene.txt,
or a mesh file. Exit codes: 0 done, 1 every step rejected, 2 bad input, 130 interrupted."""

FIGURES_HELP = """\
Redraw every figure in docs/ from the engine; each figure NAME is NAME.png and NAME.json
(the numbers drawn in it), so a new run can be compared with a committed one.

  volume_SCENE          volume / rest volume over time, linear vs corotational, for each
                        built-in scene (volume_bunny, volume_cube, ... volume_torsion)
  torsion_length        the torsion bar's length along its axis, and its thickness, over time
  frame25_builtin       epcot and cube86 at frame 25, linear vs corotational (coursework Figure 1)
  frame25_coursework    the same from the coursework's own *-scene.txt files (needs --cggs)
  epcot_compare         epcot at t = 2 s, linear left, corotational right (the README's picture)
  epcot_compare_volume  the same, coloured by volume ratio
  accuracy_vs_time      the benchmark's plot, redrawn from docs/benchmark.json (`bench --docs`)
  hard_case_energy      a near-incompressible cube at dt 0.5 s: the one-solve step gains energy,
                        the Newton step never does
  integrator_order      error against dt: backward Euler (first order) against BDF2 and the
                        trapezoidal rule (second order)
  energy_drift          energy over 10 s of a free spinning, twisting bar, each integrator

All of them take a few minutes on 2 CPU cores. docs/viewer.png is not made here: it is a
screenshot of the window (`view epcot --compare`, then the p key)."""


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage mistake as one `error:` line and exit code 2, and takes
    options only as written in full (`--steps` is not taken for `--steps-per-frame`)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message):
        print(f"error: {self.prog}: {one_line(message)}{self.option_hint(message)} (see --help)", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)

    def option_hint(self, message) -> str:
        """'; did you mean --steps?' for a mistyped option (`--stpes`) or a number given to a choice
        (`--step 10`); '; --frames is an option of export' for another command's option. The top-level
        parser reports a command's unknown options, so the command is looked for in `self.argv`."""
        commands = getattr(self, "commands", {})
        given = [commands[word] for word in getattr(self, "argv", []) if word in commands][:1]
        actions = dict(self._option_string_actions)
        for command in given or commands.values():
            actions |= command._option_string_actions
        choice = re.match(r"argument (--[\w-]+): invalid choice: '(.*)' \(choose", message)
        if choice:
            option, value = choice.groups()
            close = [word for word in difflib.get_close_matches(option, sorted(set(actions) - {option}))
                     if takes_number(actions[word], value)]
            return f"; did you mean {close[0]}?" if close else ""
        unknown = message.removeprefix("unrecognized arguments: ").split() if message.startswith("unrecognized") else []
        for word in (word.split("=")[0] for word in unknown if word.startswith("--")):
            owners = [name for name, command in commands.items() if word in command._option_string_actions]
            if owners:
                return f"; {word} is an option of {' and '.join(owners)}"
            close = difflib.get_close_matches(word, sorted(actions), n=1)
            if close:
                return f"; did you mean {close[0]}?"
        return ""

    def print_help(self, file=None):
        """argparse's, except that a write that fails is not ignored: help sent to a full disk
        (`help export > /dev/full`) is an error, not lost with exit code 0."""
        (file or sys.stdout).write(self.format_help())

    def exit(self, status=0, message=None):
        """After --help or --version: what they printed is flushed here, so that a gone reader
        (`--version | true`) ends the run quietly, as in main(); a full disk reaches main() as an OSError."""
        try:
            sys.stdout.flush()
        except BrokenPipeError:
            status = reader_gone()
        super().exit(status, message)


def takes_number(action, text) -> bool:
    """True when the option of argparse `action` reads `text` as its number (--steps reads 10)."""
    try:
        return isinstance(action.type(text), (int, float))
    except (TypeError, ValueError, argparse.ArgumentTypeError):      # no type (a flag), or not its number
        return False


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
SCENE_HELP = "built-in name (see `scenes`), .toml scene, coursework *-scene.txt, or a mesh file"


def add_common(p):
    """Options every command that runs the engine shares."""
    p.add_argument("--arch", default="cpu", choices=["cpu", "gpu", "auto"],
                   help="Taichi backend; auto picks CUDA when present, else the CPU (default cpu)")
    p.add_argument("--precision", default="f32", choices=["f32", "f64"], help="float type (default f32)")
    p.add_argument("--debug", action="store_true", help="show tracebacks and enable Taichi's checks")


def add_scene_options(p, scene_required=True):
    """The scene and what may override it."""
    if scene_required:
        p.add_argument("scene", help=SCENE_HELP)
    else:
        p.add_argument("scene", nargs="?", default=DEFAULT_SCENE, help=f"{SCENE_HELP} (default {DEFAULT_SCENE})")
    m = p.add_mutually_exclusive_group()
    m.add_argument("--linear", dest="method", action="store_const", const="linear",
                   help="every body uses linear FEM")
    m.add_argument("--corotational", dest="method", action="store_const", const="corotational",
                   help="every body uses corotational FEM")
    m.add_argument("--naive", dest="method", action="store_const", const="corotational-naive",
                   help="every body uses the tempting but wrong f = -R Ke R^T (x - X), for teaching "
                        "(see docs/method.md; one linear solve per step)")
    p.add_argument("--solver", choices=["pcg", "jacobi"], help="linear solver (scene default: pcg)")
    p.add_argument("--tol", type=POSITIVE, help="relative residual tolerance of the solve")
    p.add_argument("--max-iters", type=COUNT, help="iteration cap of the solve")
    p.add_argument("--step", choices=["newton", "single"],
                   help="newton: minimise the incremental potential, energy never rises (default); "
                        "single: one linear solve per step, rotations frozen (cheaper, can gain energy)")
    p.add_argument("--integrator", choices=INTEGRATOR_CHOICES,
                   help="auto (default): trapezoidal, or bdf2 in a scene with a ground; trapezoidal: second "
                        "order, keeps energy and angular momentum (projected onto them), the most accurate; "
                        "bdf2: second order, damps the fastest modes (the ground's stiff contact); "
                        "backward-euler: first order, damps fast motion. --set solver.rho_infinity=R (0..1) "
                        "gives the trapezoidal rule numerical dissipation of the modes dt cannot follow")
    p.add_argument("--dt", type=POSITIVE, help="time step, s")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a scene value, e.g. --set body.soft.mesh.cells=[8,8,8]; "
                        "file paths in it are relative to the current folder")
    p.add_argument("--contact", action="store_true",
                   help="contact between bodies and within each: the scene's [effects] contact, or "
                        "distance 0.01 m and no friction where it has none")
    p.add_argument("--allow-large", action="store_true",
                   help="lift the size limits (the tets half the backend's memory holds, 8192 pixels a side)")
    add_common(p)


def build_parser(prog="main.py"):
    parser = Parser(prog=prog, description="Linear and corotational soft bodies (tet FEM, Taichi).",
                    epilog=EPILOG.format(prog=prog), formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--version", action=Version, nargs=0, help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    parser.commands = sub.choices    # {name: that command's parser}

    p = sub.add_parser("simulate", help="run a scene without a window and summarise it")
    add_scene_options(p)
    p.add_argument("--steps", type=STEPS, default=100, help="number of steps (default 100)")
    p.add_argument("--stats", metavar="FILE.jsonl",
                   help="one JSON object per step ('-': to stdout, and the summary to stderr)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing stats file")
    p.add_argument("--profile", action="store_true",
                   help="after the run, a table of where the steps' time went, kernel by kernel "
                        "(Taichi's kernel profiler; the first step is left out)")

    p = sub.add_parser("export", help="render frames (PNG) and a video without a display")
    add_scene_options(p, scene_required=False)
    p.add_argument("--frames", type=COUNT, default=120, help="number of frames (default 120)")
    p.add_argument("--out", help="folder for the PNG frames (default: a new out/SCENE-N folder)")
    p.add_argument("--video", metavar="FILE", help="also write a .mp4 (H.264) or .gif")
    p.add_argument("--size", default="640x480", help="image size WxH (default 640x480, at most 8192 a side)")
    p.add_argument("--speed", type=POSITIVE, default=1.0,
                   help="simulated seconds per second of video (default 1: real time)")
    p.add_argument("--fps", type=POSITIVE, help="video frame rate (default: what plays at --speed with a whole "
                                                "number of steps between frames, as near 30 as that allows: "
                                                "25 at the usual dt of 0.02 s, 2 steps a frame)")
    p.add_argument("--steps-per-frame", type=COUNT,
                   help="simulation steps per frame (default: what --speed and --fps ask for)")
    p.add_argument("--compare", action="store_true", help="left copy linear, right copy corotational")
    p.add_argument("--color", default="body", choices=["body", "volume", "strain"], help="colour mode")
    p.add_argument("--contact-points", action="store_true", help="mark where bodies touch (needs contact)")
    p.add_argument("--renderer", default="auto", choices=["auto", "ggui", "software"],
                   help="auto: the built-in software renderer (same picture, no Vulkan, steady memory); "
                        "ggui: GGUI offscreen (needs Vulkan; Taichi 1.7 keeps ~250 kB per frame)")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty folder / replace the video")

    p = sub.add_parser("view", help="interactive window: click to push, c toggles corotation")
    add_scene_options(p, scene_required=False)
    p.add_argument("--compare", action="store_true", help="left copy linear, right copy corotational")
    p.add_argument("--stats", metavar="FILE.jsonl", help="one JSON object per rendered frame, with events "
                                                         "('-' for stdout)")
    p.add_argument("--size", default="1280x720", help="window size WxH (default 1280x720)")
    p.add_argument("--out", default="out", help="folder for screenshots (p) and recordings (v) (default out)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing stats file")

    p = sub.add_parser("bench", help="what accuracy costs in time: tables and a plot")
    p.add_argument("--quick", action="store_true", help="2 scenes to 1 s: a check, no frontier conclusions (~6 min)")
    p.add_argument("--out", default="out/bench", help="output folder (default out/bench)")
    p.add_argument("--scenes", nargs="+", help="scenes to measure (default: all seed scenes and boxes)")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty folder")
    p.add_argument("--docs", action="store_true",
                   help="replace docs/benchmark.md, docs/benchmark.json and docs/accuracy_vs_time.png (with its "
                        "numbers, .json) instead of writing into --out (the full benchmark only)")
    add_common(p)

    p = sub.add_parser("figures", help="redraw every figure in docs/, with the numbers behind each",
                       description=FIGURES_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/figures", metavar="DIR",
                   help="folder for NAME.png and NAME.json (default out/figures; "
                        "`--out docs --overwrite` updates the committed figures)")
    p.add_argument("--only", nargs="+", metavar="NAME", help="make only these figures (names above)")
    p.add_argument("--cggs", metavar="FOLDER", help="the coursework's folder of *-scene.txt and .mesh files: "
                                                    "also draw frame25_coursework")
    p.add_argument("--bench", metavar="FILE.json", help="the benchmark results to redraw "
                                                        "(default docs/benchmark.json, from `bench --docs`)")
    p.add_argument("--quick", action="store_true", help="a quarter of the simulated time, to try the "
                                                        "command (not for docs/)")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty folder")
    add_common(p)

    p = sub.add_parser("plot", help="draw --stats files against t: energies, volume, iterations, residual")
    p.add_argument("stats", nargs="+", metavar="STATS.jsonl", help="files written by `simulate --stats`")
    p.add_argument("--out", metavar="FILE.png", help="the picture, FILE.json its numbers (default: STATS.png)")
    p.add_argument("--quantity", nargs="+", metavar="KEY", help="draw these keys instead, a panel each")
    p.add_argument("--overwrite", action="store_true", help="replace an existing picture and its numbers")

    sub.add_parser("scenes", help="list the built-in scenes")
    p = sub.add_parser("help", help="list the commands, or show one command's options")
    p.add_argument("topic", nargs="?", metavar="COMMAND", help="the command to explain")
    return parser


class Version(argparse.Action):
    """--version, reading the version only when asked (importing the engine takes a second)."""

    def __call__(self, parser, namespace, values, option_string=None):
        from fem import __version__
        with contextlib.suppress(BrokenPipeError):     # parser.exit says so
            print(f"softfem {__version__}")
        parser.exit()


def default_arguments():
    """What a bare `main.py` does: the window where a display is usable, otherwise an
    export of the default scene into a folder of its own (out/epcot, out/epcot-2, ...)."""
    problem = display_problem()
    if problem is None:
        return ["view"]
    out = fresh_folder(DEFAULT_SCENE)
    print(f"no window ({problem.split(';')[0]}): exporting {DEFAULT_SCENE} (linear vs corotational) "
          f"to {out}/", file=sys.stderr)
    return ["export", DEFAULT_SCENE, "--compare", "--frames", str(DEFAULT_FRAMES), "--out", str(out),
            "--video", str(out / f"{DEFAULT_SCENE}.mp4")]


def fresh_folder(name, parent="out"):
    """parent/name, or parent/name-2, -3, ...: the first that does not exist or is an empty folder,
    so that earlier output is never touched."""
    out, copy = Path(parent) / name, 1
    while out.exists() and (not out.is_dir() or any(out.iterdir())):
        copy += 1
        out = Path(parent) / f"{name}-{copy}"
    return out


def command_taking(argv, commands):
    """The first of simulate, export, view that takes every option in argv (for the hint
    after `main.py --steps 5`); else export."""
    options = [word.split("=")[0] for word in argv if word.startswith("--")]
    for name in ("simulate", "export", "view"):
        if all(option in commands[name]._option_string_actions for option in options):
            return name
    return "export"


def names_a_scene(word) -> bool:
    """True for a built-in scene's name or an existing file (`main.py epcot --linear` lacks a
    command; it does not misspell `export`)."""
    import scenes
    return word in scenes.builtin_scenes() or Path(word).exists()


def command_hint(word, commands) -> str:
    """'; did you mean simulate?' for a mistyped command, else ''."""
    close = difflib.get_close_matches(word, list(commands), n=1)
    return f"; did you mean {close[0]}?" if close else ""


def reader_gone():
    """The reader of stdout went away (`... --stats - | head`): stop quietly, as other tools do, with
    SIGPIPE's exit code; stdout goes to /dev/null so that Python's final flush does not fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):   # stdout without a file descriptor (tests)
        pass
    return EXIT_BROKEN_PIPE


def dispatch(args, parser):
    if args.command == "help":
        commands = parser.commands
        if args.topic is not None and args.topic not in commands:
            parser.error(f"help: no command {args.topic!r}{command_hint(args.topic, commands)}; "
                         f"commands: {', '.join(commands)}")
        (commands[args.topic] if args.topic else parser).print_help()
        return 0
    if args.command == "scenes":
        import scenes
        for name, description in scenes.builtin_scenes().items():
            print(f"{name:10s} {description}")
        print("\nor a file: a .toml scene, a coursework *-scene.txt, a surface mesh (.obj .stl .ply .off) "
              "or a tet mesh (.mesh .msh .vtk .vtu)")
        return 0
    try:
        os.getcwd()                 # Taichi's start and every relative path need it
    except FileNotFoundError:
        raise FemError("the current folder was removed; change to one that exists") from None
    if args.command == "export" and args.out is None:
        args.out = str(fresh_folder(Path(args.scene).stem))
    if args.command == "plot" and args.out is None:
        args.out = str(Path(args.stats[0]).with_suffix(".png"))
    for attribute, option, kind in OUTPUTS.get(args.command, []):
        value = getattr(args, attribute, None)
        if value is not None and value != "-":
            check_output(value, option, kind)
    # Each command is the module of its name, imported only when run (most import the engine).
    return importlib.import_module(f"app.commands.{args.command}").run(args)


def main(argv=None) -> int:
    """Run the command line `argv` (default sys.argv[1:]); returns the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if sys.stdout is None:      # `main.py ... >&-`: what is meant for stdout is dropped
        # /dev/null takes the closed descriptor 1, so that no file this run opens gets it.
        sys.stdout = open(os.devnull, "w")
    for stream in (sys.stdout, sys.stderr):     # a name the terminal cannot show (PYTHONIOENCODING=ascii)
        with contextlib.suppress(AttributeError, ValueError):        # a stream without reconfigure (tests)
            stream.reconfigure(errors="backslashreplace")
    parser = build_parser(program_name())
    commands = parser.commands
    if not argv:
        argv = default_arguments()
    elif not any(word in commands for word in argv) and not {"-h", "--help", "--version"} & set(argv):
        if not argv[0].startswith("-") and not names_a_scene(argv[0]) and command_hint(argv[0], commands):
            parser.error(f"no command {argv[0]!r}{command_hint(argv[0], commands)}; "
                         f"commands: {', '.join(commands)}")
        # Flags alone (`main.py --linear`) start nothing: they belong to a command.
        example = " ".join(argv if not argv[0].startswith("-") else [DEFAULT_SCENE, *argv])
        parser.error(f"no command given; commands: {', '.join(commands)}; "
                     f"e.g. `{parser.prog} {command_taking(argv, commands)} {example}`")
    parser.argv = argv                  # for option_hint
    try:
        args = parser.parse_args(argv)
    except BrokenPipeError:             # --help to a reader that went away
        return reader_gone()
    except OSError as error:            # --help or --version into a full disk
        if error.errno not in outputs.WRITE_ERRORS:
            raise
        return stdout_failed(error)
    if args.command is None:
        parser.error(f"no command given; commands: {', '.join(commands)}")

    from fem import limits
    try:
        with interrupt_on_sigterm(), limits.lifted(getattr(args, "allow_large", False)):
            code = dispatch(args, parser)
            sys.stdout.flush()          # here, where a full disk or a closed pipe is caught
            return code
    except FemError as e:
        if args.debug:
            raise
        hint = "; --allow-large lifts the limit" if isinstance(e, SizeLimitError) else ""
        print(f"error: {one_line(e)}{hint}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        # The commands say what they kept; this is an interruption before they wrote anything.
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return reader_gone()
    except OSError as e:
        if args.debug or e.errno not in (errno.ENAMETOOLONG, *outputs.WRITE_ERRORS):
            raise
        if e.filename is None:
            return stdout_failed(e)
        print(f"error: {one_line(outputs.write_failed(e.filename, e))}", file=sys.stderr)
        return EXIT_BAD_INPUT


def stdout_failed(error: OSError) -> int:
    """Printing to stdout failed (a full disk, /dev/full): one error line, exit code 2. Stdout
    stays unusable until the end, so it goes to /dev/null, as reader_gone() does."""
    reader_gone()
    print(f"error: {outputs.write_failed('standard output', error)}", file=sys.stderr)
    return EXIT_BAD_INPUT
