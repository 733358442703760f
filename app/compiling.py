"""Saying what a start is doing while Taichi compiles the kernels (most of a start's time).

    with Compiling("epcot", key) as compiling:
        sim = fem.Simulation(scene)
        sim.step()                    # the kernels compile here, and the line says how far along

On a terminal one line is rewritten in place: "epcot: compiling kernels, 12 of 45 (3 s)"; it is
cleared when the work is done. Elsewhere (a log, a pipe) a line is printed once the compiling has
taken a second and every ten seconds after, and a last one says how long it took in all, so a
log shows where the start went. "of 45" is the count the same command compiled the last time
(kept beside Taichi's offline cache); the first time there is none, and the line counts up.
"""

import json
import os
import sys
import time

from fem import runtime

FIRST_LINE_S = 1.0       # off a terminal: the first line after this long, then one every
LOG_INTERVAL_S = 10.0    # this long
COUNTS_FILE = "softfem-kernel-counts.json"


_open = []               # the Compiling contexts open now (start_done ends them)


def start_done():
    """The start is over wherever it is told (an export's first stepped frame): end every open
    Compiling as its done() does."""
    for compiling in list(_open):
        compiling.done()


class Compiling:
    """Reports kernels compiled on `stream` (stderr) while the context is open. key: what decides
    which kernels a command compiles (scene, switches, precision), to remember their count by."""

    def __init__(self, name, key, stream=None):
        self.name, self.key = name, key
        self.stream = stream or sys.stderr
        self.terminal = _isatty(self.stream)
        self.kernels = 0
        self.expected = remembered_counts().get(key)
        self.start = self.last_line = time.monotonic()
        self.shown = False

    def __enter__(self):
        runtime.compile_listeners().append(self.heard)
        _open.append(self)
        return self

    def __exit__(self, kind, *exc):
        self.done(remember=kind is None)
        return False

    def done(self, remember=True):
        """The start is over (the first step or frame is done): stop listening, end the line, and
        remember the count for the next start of the same command."""
        if self in _open:
            _open.remove(self)
        if self.heard not in runtime.compile_listeners():
            return
        runtime.compile_listeners().remove(self.heard)
        if self.terminal and self.shown:
            self.write("\r\033[K")
        elif self.shown:
            kernels = f"{self.kernels} kernel{'s' if self.kernels != 1 else ''}"
            self.write(f"{self.name}: compiled {kernels} in {time.monotonic() - self.start:.1f} s\n")
        if remember and self.kernels:
            remember_count(self.key, self.kernels)

    def heard(self, kernel_name):
        """A kernel is about to compile: count it, and say so when it is time."""
        self.kernels += 1
        now = time.monotonic()
        if self.terminal:
            self.shown = True
            self.write(f"\r\033[K{self.status(now)}")
        elif now - self.start >= FIRST_LINE_S and (not self.shown or now - self.last_line >= LOG_INTERVAL_S):
            self.shown, self.last_line = True, now
            self.write(self.status(now) + "\n")

    def status(self, now):
        of = f" of {self.expected}" if self.expected and self.expected >= self.kernels else ""
        return f"{self.name}: compiling kernels, {self.kernels}{of} ({now - self.start:.0f} s)"

    def write(self, text):
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError, AttributeError):     # stderr closed or gone: nothing to say it on
            pass


def _isatty(stream):
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def counts_path():
    """Where the counts are kept: in the folder of Taichi's offline cache (Taichi must be running)."""
    return os.path.join(runtime.cache_folder(), COUNTS_FILE)


def remembered_counts():
    """{key: kernels compiled} of earlier starts ({} when none, or the file is unreadable)."""
    path = counts_path()
    try:
        with open(path) as f:
            counts = json.load(f)
        return counts if isinstance(counts, dict) else {}
    except (OSError, TypeError, ValueError):
        return {}


def remember_count(key, kernels):
    """Keep `kernels` as the count of `key`'s start (written atomically; a failure is ignored:
    the count only makes the next line say "of N")."""
    path = counts_path()
    counts = remembered_counts()
    counts[key] = kernels
    temporary = f"{path}.{os.getpid()}.tmp"
    try:
        with open(temporary, "w") as f:
            json.dump(counts, f, indent=0, sort_keys=True)
        os.replace(temporary, path)
    except OSError:
        try:
            os.unlink(temporary)
        except OSError:
            pass


# Options that do not change which kernels a command compiles.
NOT_COMPILED = {"steps", "stats", "overwrite", "out", "frames", "video", "speed", "debug", "size"}


def start_key(args):
    """What decides the kernels of the command line `args` (argparse's namespace), as a string."""
    kept = {name: value for name, value in sorted(vars(args).items()) if name not in NOT_COMPILED}
    return json.dumps(kept, default=str, sort_keys=True)
