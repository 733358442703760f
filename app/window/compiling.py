"""The window while a scene's kernels compile: a part of `Viewer` (app/window/viewer.py), whose
attributes it reads and sets. Between two kernels (fem.runtime's compile listeners) it shows the
picture at rest and "compiling kernels, 12 of 40", and keeps the clicks and keys it reads for the
first frame that steps."""

import argparse
import time
from pathlib import Path

import taichi as ti

from app.compiling import Compiling, start_key
from app.render.ggui import _quiet_taichi
from app.window.panel import panel_width
from fem import runtime

# While kernels compile, a frame at most this often, and in at most a tenth of the time (a frame
# takes 40 ms on a software Vulkan driver).
COMPILING_FRAME_SECONDS = 0.1
COMPILING_FRAME_SHARE = 0.1


class WindowClosed(Exception):
    """The window was closed (Esc, or its close button) while kernels compiled."""


class CompilingFrames:
    """Frames and input while kernels compile (a mixin: the Viewer holds the state)."""

    def start_compiling(self, ref):
        """Count the kernels the scene's start compiles (app.compiling: "k of N", N the count of
        the same start the last time), and show frames between them (between_kernels)."""
        if self.compiling is not None:       # a scene chosen in the first frame of the one before
            self.end_compiling()
        key = start_key(argparse.Namespace(**dict(vars(self.args), scene=str(ref))))
        # A scene after another compiles only what that one did not: another count.
        key = f"view {key}" + (" after another scene" if self.sim is not None else "")
        self.compiling = Compiling(Path(str(ref)).stem, key).__enter__()
        runtime.compile_listeners().append(self.between_kernels)

    def end_compiling(self):
        """The scene steps: stop listening, remember the count, and say in the events what it took."""
        runtime.compile_listeners().remove(self.between_kernels)
        self.compiling.done()
        self.events.append({"type": "compiled", "kernels": self.compiling.kernels,
                            "seconds": round(time.monotonic() - self.compiling.start, 2)})
        self.compiling = None

    def between_kernels(self, kernel_name):
        """Heard before each kernel compiles while a scene starts (fem.runtime.compile_listeners):
        at most every COMPILING_FRAME_SECONDS, a frame with the picture at rest and a line saying
        how far the compiling is, which keeps the window answering; the input read meanwhile
        waits for the first frame that steps. It never steps or pushes (the kernels are not
        ready), and it hears nothing while a frame is drawn (drawing compiles kernels of its own)."""
        if self.busy or time.perf_counter() < self.next_compiling_frame:
            return
        self.busy = True
        try:
            self.waiting += self.read_input()
            if not self.window.running or any(e.pressed and e.key == ti.ui.ESCAPE for e in self.waiting):
                raise WindowClosed
            self.show_compiling()
        finally:
            self.busy = False

    def show_compiling(self):
        """A frame while kernels compile: the picture drawn last (the backdrop before the first),
        and a panel saying what is compiling."""
        start = time.perf_counter()
        width = panel_width(self.width)
        with _quiet_taichi():
            self.canvas.set_image(self.picture if self.frame else self.backdrop)
            with self.gui.sub_window("softfem", 1 - width, 0.0, width, 1.0) as g:
                self.draw_compiling(g)
            self.window.show()
        end = time.perf_counter()
        self.next_compiling_frame = end + max(COMPILING_FRAME_SECONDS, (end - start) / COMPILING_FRAME_SHARE)
