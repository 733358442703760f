"""Writing frames: a video (MP4 through ffmpeg, or GIF through Pillow) never put in place broken,
and a thread that writes each frame while the next one is made.

Frames go to a temporary file beside the video; when the encoder is done, its file is
checked (an MP4's boxes must fill it and hold the index, a GIF must end with its trailer)
before it is renamed into place: ffmpeg on a full disk leaves an MP4 with no index and
still exits normally.
"""

import contextlib
import os
import shutil
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import imageio.v2
import numpy as np
from PIL import Image

from app import outputs
from app.files import atomic_path, interrupts_deferred
from fem.errors import FemError

# H.264 codes 16 x 16 pixel blocks: ffmpeg would resize any other frame size.
MACRO_BLOCK = 16
# Frame rates a video can be written at, per format: imageio hands ffmpeg the rate with two
# decimals (below 0.1 it would be off by 10 % or more, at 0.004 zero: a file with no stream),
# and a GIF stores each frame's delay as whole hundredths of a second (at most 655 s); at
# 1000 frames per second imageio reads the MP4's rate back as 0 (500 reads back right).
VIDEO_FPS = {".mp4": (0.1, 500.0), ".gif": (0.1, 100.0)}
# Free space below which a failed encoder is put down to a full disk.
FULL_DISK_BYTES = 1 << 20


class VideoFailed(FemError):
    """The encoder could not finish the video (a full disk, most often); nothing was put in place."""


class VideoWriter:
    """Appends frames to an MP4 (H.264, yuv420p) or GIF written under a temporary
    name; leaving the `with` block normally, or by an interruption (Ctrl-C, SIGTERM)
    after some frames, renames it into place once the encoder has finished it whole;
    any other exception, or an encoder that failed (VideoFailed), removes it.
    With path None it does nothing (active is False)."""

    def __init__(self, path: Path | None, fps: float, overwrite: bool = True):
        self.path, self.fps, self.overwrite = path, fps, overwrite
        self.active = path is not None
        self.temporary = atomic_path(path) if self.active else None
        self.writer = None
        self.frames = 0
        self.placed = False                 # the finished video is in place

    def __enter__(self):
        if not self.active:
            return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.suffix.lower() == ".mp4":
            # Quiet: a failed encoder is reported in one line of ours (VideoFailed).
            self.writer = imageio.v2.get_writer(
                self.temporary, format="FFMPEG", mode="I", fps=self.fps, codec="libx264",
                pixelformat="yuv420p", quality=8, macro_block_size=MACRO_BLOCK,
                ffmpeg_log_level="quiet")
        else:
            self.writer = GifWriter(self.temporary, self.fps)
        return self

    def append(self, image: np.ndarray):
        """Add one frame, (H, W, 3) uint8, every frame the same size."""
        with interrupts_deferred():
            try:
                self.writer.append_data(image)
            except OSError as error:          # the encoder stopped: its pipe broke, or the disk filled
                raise self.failed(error) from None
            self.frames += 1

    def finish(self):
        """Close the encoder and check that it wrote the whole file; VideoFailed if not."""
        try:
            self.writer.close()
        except OSError as error:
            raise self.failed(error) from None
        if not video_complete(self.temporary):
            raise self.failed()

    def failed(self, error: OSError | None = None) -> VideoFailed:
        """The error for a video the encoder could not finish, with the likeliest reason."""
        try:
            free = shutil.disk_usage(self.path.parent).free
        except FileNotFoundError:
            return VideoFailed(f"{self.path}: its folder was removed while this run wrote into it; "
                               "the video was not written")
        if error is not None and error.errno in outputs.WRITE_ERRORS or free < FULL_DISK_BYTES:
            reason = "no space left on device"
        elif error is not None:     # imageio's error: the broken pipe, or ffmpeg's exit status
            said = (str(error).strip().splitlines() or [""])[0][:120]
            reason = f"the encoder failed ({type(error).__name__}: {said})"
        else:
            reason = "the encoder failed (its file is incomplete)"
        return VideoFailed(f"{self.path}: {reason}; the video was not written")

    def __exit__(self, kind, error, traceback):
        if not self.active:
            return False
        # Interrupted, the video keeps the frames it has, as the PNGs do.
        keep = kind is None or (issubclass(kind, (KeyboardInterrupt, FemError)) and self.frames > 0
                                and not issubclass(kind, VideoFailed))
        try:
            if keep:
                with interrupts_deferred():
                    self.finish()
                    outputs.put_in_place(self.temporary, self.path, self.overwrite)
                    self.placed = True
            else:
                with contextlib.suppress(Exception):   # a half-written video is discarded anyway
                    self.writer.close()
        finally:
            with contextlib.suppress(OSError):
                os.unlink(self.temporary)
        return False


class WriterThread:
    """Calls write(*frame) on a thread of its own for each frame handed to `put`, one at a time,
    while the caller makes the next frame: Pillow's PNG encoder (zlib) and the pipe into ffmpeg
    let go of Python's lock (the GIL) while they work. At most two frames are held: the one
    being written and the one being made.

    put hands a frame over once the one before is written, and raises that frame's error in the
    caller's thread (FemError for a full disk or a removed folder, VideoFailed, KeyboardInterrupt):
    the loop stops at its next frame, and no frame is begun after one that failed. Leaving the
    `with` block waits for the frame being written; leaving it normally raises that frame's error.

    Python runs signal handlers in the main thread only, at its next instruction: a Ctrl-C or
    SIGTERM that comes while a frame is written is raised before put sees that frame done, so
    before it hands the next one over. The frame being written is finished and no later frame
    is begun, as when the loop wrote its frames itself.

    busy_ms: the thread's time on each frame; waited_ms: the caller's time in each put (ms).
    """

    def __init__(self, write):
        self.write = write
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-writer")
        self.pending = None                     # the frame being written (a Future), if any
        self.busy_ms, self.waited_ms = [], []

    def put(self, *frame):
        """Wait for the frame before, then have this one written."""
        start = time.perf_counter()
        self.wait()
        self.waited_ms.append(1e3 * (time.perf_counter() - start))
        self.pending = self.pool.submit(self.timed, *frame)

    def wait(self):
        """Wait until the frame being written is done; raise its error."""
        pending, self.pending = self.pending, None
        if pending is not None:
            pending.result()

    def timed(self, *frame):
        start = time.perf_counter()
        self.write(*frame)
        self.busy_ms.append(1e3 * (time.perf_counter() - start))

    def __enter__(self):
        return self

    def __exit__(self, kind, error, traceback):
        try:
            if kind is None:
                self.wait()
        finally:
            # Stopped by an error or an interruption: the frame being written is finished
            # (its files whole and counted); an error of its own would not be news.
            self.pool.shutdown(wait=True)
        return False


class GifWriter:
    """A GIF made with Pillow: the frames are kept, and the file written once, on close."""

    def __init__(self, path: Path, fps: float):
        self.path, self.fps, self.frames = path, fps, []

    def append_data(self, image: np.ndarray):
        self.frames.append(Image.fromarray(image))

    def close(self):
        frames, self.frames = self.frames, []
        # GIF delays are whole hundredths of a second; loop=0 repeats forever.
        frames[0].save(self.path, format="GIF", save_all=True, append_images=frames[1:],
                       duration=1000.0 / self.fps, loop=0)


def video_complete(path: Path) -> bool:
    """True when the encoder's file is whole: an MP4's top-level boxes fill the file exactly
    and hold the movie header (moov, with a track) and the media data (mdat); a GIF ends with
    its trailer byte. A full disk or a killed encoder leaves neither."""
    try:
        with open(path, "rb") as f:
            if Path(path).suffix.lower() == ".gif":
                head = f.read(4)
                f.seek(-1, os.SEEK_END)
                return head == b"GIF8" and f.read(1) == b"\x3b"
            return mp4_complete(f, os.fstat(f.fileno()).st_size)
    except OSError:
        return False


def mp4_complete(f, length: int) -> bool:
    """mp4: the walk over the top-level boxes (size, type) of the open file f of length bytes."""
    kinds, at, moov = set(), 0, b""
    while at + 8 <= length:
        f.seek(at)
        header = f.read(16)
        size, kind = int.from_bytes(header[:4], "big"), header[4:8]
        if size == 1:                                   # a 64-bit size follows
            size = int.from_bytes(header[8:16], "big")
        elif size == 0:                                 # the last box, to the end of the file
            size = length - at
        if size < 8:
            return False
        if kind == b"moov":
            f.seek(at)
            moov = f.read(size)
        kinds.add(kind)
        at += size
    return at == length and b"mdat" in kinds and b"trak" in moov
