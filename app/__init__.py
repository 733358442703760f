"""App layer: the command line, the window, the exporter and the benchmark, which read the engine's state.

Rooms by role, each importing only downwards (tests/test_layout.py checks it):

    cli.py       the command line (`main.py`, `softfem`): parses, checks outputs, dispatches
    commands/    one module per command: simulate, export, view, bench, figures, plot
    render/      pictures of a frame: camera, the renderers (base, GGUI, software), colours, overlays
    window/      the interactive window behind `view`: the viewer, its controls and panel,
                 picking a body and orbiting the camera
    bench/       the benchmark behind `bench`: plan, measure, conclusions, report and plot,
                 the direct baseline and the start-up timings

The plumbing that every room uses sits here at the top, one small module each: files.py
(atomic writes, overwrite checks, interrupts), outputs.py (special files, locked folders, a
killed run's leftovers, full disks), progress.py (progress bars and log lines), device.py (the
Taichi back end), display.py (whether a window can open), video.py (an MP4 or GIF, checked
before it is put in place), and program_name() below. They import nothing from the rooms, and
a sub-package of six small modules would only lengthen every import.
"""

import sys
from pathlib import Path

# Exit codes of every command: done, the run failed (every step rejected), bad input
# (one `error:` line), interrupted (Ctrl-C or SIGTERM; complete files kept), the reader
# of stdout went away (`| head`; 128 + SIGPIPE, as a shell reports a tool killed by it).
EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 0, 1, 2, 130, 141


def program_name():
    """'softfem' when run as the installed command, else 'main.py' (for the commands a message
    suggests; here, not in cli.py, so that every room can name them)."""
    return "softfem" if Path(sys.argv[0]).name == "softfem" else "main.py"
