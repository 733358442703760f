"""Progress of a long run on stderr, fit for a terminal and for a log file.

On a terminal: a tqdm bar. Otherwise (a log, a CI job, a pipe) a bar's
carriage-return updates would pile up into thousands of lines, so instead one
plain line every `LOG_INTERVAL` seconds, and none for a run shorter than that.
"""

import sys
import time

from tqdm import tqdm

LOG_INTERVAL = 10.0   # seconds between lines when stderr is not a terminal


class Progress:
    """Counts done units out of total; use as a context manager and call update() per unit.

    total: units in the run; unit: what is counted ("frame", "step");
    description: the run's name, shown first.
    """

    def __init__(self, total: int, unit: str, description: str, stream=None):
        self.stream = stream or sys.stderr
        self.total, self.unit, self.description = total, unit, description
        self.done = 0
        self.start = self.last_line = time.monotonic()
        self.bar = (tqdm(total=total, unit=unit, desc=description, file=self.stream)
                    if self.stream.isatty() else None)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.close()
        return False

    def set_description(self, description: str):
        """Name what is running now (as tqdm's set_description)."""
        self.description = description
        if self.bar is not None:
            self.bar.set_description(description)

    def update(self, count: int = 1):
        self.done += count
        if self.bar is not None:
            self.bar.update(count)
            return
        now = time.monotonic()
        if now - self.last_line >= LOG_INTERVAL and self.done < self.total:
            self.last_line = now
            print(f"{self.description}: {self.done}/{self.total} {self.unit}s "
                  f"({100 * self.done / self.total:.0f} %) after {now - self.start:.0f} s",
                  file=self.stream, flush=True)
