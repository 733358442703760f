"""`main.py view`: the interactive window (Taichi GGUI); the window itself is app/window/."""

import sys

import fem
from app import EXIT_INTERRUPTED, device, outputs
from app.display import display_problem
from app.files import refuse_overwrite
from app.window.compiling import WindowClosed
from app.window.viewer import Viewer


def run(args) -> int:
    check_display()
    width, height = parse_size(args.size)
    to_file = args.stats is not None and args.stats != "-"
    if to_file:
        refuse_overwrite(args.stats, args.overwrite)
    device.start(args)
    try:
        viewer = Viewer(args, width, height)
    except WindowClosed:              # closed while the first scene compiled
        return 0
    try:
        if to_file:
            with outputs.open_stream(args.stats, args.overwrite) as stats_file:
                viewer.loop(stats_file)
        else:
            viewer.loop(sys.stdout if args.stats == "-" else None)
    except WindowClosed:
        pass
    except KeyboardInterrupt:
        viewer.stop_video()
        kept = f"; kept the {viewer.frame} complete rows in {args.stats}" if to_file else ""
        print(f"interrupted at frame {viewer.frame}{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


def check_display():
    """FemError unless a display is there: GLFW ends the process when it cannot open one."""
    problem = display_problem()
    if problem is not None:
        raise fem.FemError(f"view: {problem}")


def parse_size(text):
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise fem.FemError(f"--size: expected WIDTHxHEIGHT, e.g. 1280x720, got {text!r}") from None
    if not (160 <= width <= 8192 and 120 <= height <= 8192):
        raise fem.FemError(f"--size: {width}x{height} is out of range (160x120 to 8192x8192)")
    return width, height
