"""Is there a display the window can open on? Asked before Taichi is started.

GLFW (inside Taichi) ends the whole process when it cannot open a window, so
the window checks first and, when it cannot work, says why in one line.
Taichi's GLFW speaks X11 only: under Wayland the window needs XWayland
($DISPLAY set), and $WAYLAND_DISPLAY alone is not enough.
"""

import os
from pathlib import Path

HINT = ("run it under a desktop or `xvfb-run`, or use `export` for frames and videos "
        "without a display")


def display_problem(environ=None) -> str | None:
    """Why the window cannot open here (one sentence), or None when a display looks usable."""
    environ = os.environ if environ is None else environ
    display = environ.get("DISPLAY", "")
    wayland = environ.get("WAYLAND_DISPLAY", "")
    if display:
        if display.startswith(":"):       # a local X server listens on a socket we can see
            number = display[1:].split(".")[0]
            if not Path(f"/tmp/.X11-unix/X{number}").exists():
                return f"no X server on display {display}; {HINT}"
        return None
    if not wayland:
        return f"no display ($DISPLAY is not set); {HINT}"
    socket = Path(wayland) if os.path.isabs(wayland) else \
        Path(environ.get("XDG_RUNTIME_DIR", f"/run/user/{os.getuid()}")) / wayland
    if not socket.exists():
        return (f"$WAYLAND_DISPLAY is {wayland!r} but no Wayland compositor listens at {socket}, "
                f"and $DISPLAY is not set; {HINT}")
    return ("the window needs X11: $WAYLAND_DISPLAY is set but $DISPLAY is not; start XWayland "
            "(it sets $DISPLAY), or use `export` for frames and videos without a display")
