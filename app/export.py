"""`main.py export`: a scene's frames as PNG files and, optionally, a video, without a display.

    python main.py export epcot --compare --frames 150 --out out/epcot --video out/epcot.mp4

Frame 0 is the initial state; each later frame comes `steps_per_frame` time
steps after the one before. The camera and the floor stay fixed for the whole
export (the scene's camera hint, or framed on the initial state with room to
deform), so frames can be compared with each other.

Reproducible pictures: the engine and the software renderer are deterministic
on the CPU, so the PNGs depend only on the scene and the arguments. Their
overlay therefore shows simulated quantities only. Measured speed (ms per
step, ms per frame) changes from run to run: it is drawn on the video's
frames only (a video is re-encoded lossily anyway) and printed at the end.

Nothing is lost: a non-empty --out folder or an existing --video file is
refused without --overwrite, and every file is written under a temporary
name and renamed when complete, so an interrupted export (Ctrl-C, SIGTERM)
leaves only whole files.
"""

import contextlib
import os
import re
import signal
import statistics
import sys
import time
from pathlib import Path

import imageio.v2
import imageio.v3
import numpy as np
from PIL import Image, ImageDraw, ImageFont
from tqdm import tqdm

import fem
from app.camera import Camera, auto_frame
from app.colors import VertexColoring
from app.files import atomic_open, atomic_path, refuse_overwrite
from app.overlay import PANEL_COLOR, TEXT_COLOR, draw_text_overlay
from app.render import make_renderer

FRAME_NAME = "frame_{:05d}.png"
FRAME_PATTERN = re.compile(r"frame_(\d{5})\.png")
VIDEO_SUFFIXES = (".mp4", ".gif")
# H.264 codes 16 x 16 pixel blocks: ffmpeg would resize any other frame size.
MACRO_BLOCK = 16
# Room around the initial state, as a fraction of its largest extent, for bodies to deform into.
FRAMING_MARGIN = 0.25
# --compare: the gap between the copies, as a fraction of the scene's width, so
# that a linear copy inflating by half its width still does not reach the other.
COMPARE_GAP = 1.0
GROUP_NAMES = ("linear", "corotational")


def run(args) -> int:
    """Export frames (and a video) as the parsed command line `args` asks; returns the exit code."""
    width, height = frame_size(args.size, rounded=args.video is not None)
    out = Path(args.out)
    video = Path(args.video) if args.video else None
    check_arguments(args, out, video)
    refuse_overwrite(out, args.overwrite)
    if video is not None:
        refuse_overwrite(video, args.overwrite)

    fem.init(args.arch, args.precision, debug=args.debug)
    scene = fem.load_scene(args.scene, overrides=args.set)
    if args.compare:
        scene = scene.side_by_side(gap=COMPARE_GAP * scene_width(scene))
    sim = fem.Simulation(scene, method=args.method, solver=args.solver, dt=args.dt,
                         tolerance=args.tol, max_iterations=args.max_iters)
    steps = steps_per_frame(args.steps_per_frame, args.fps, sim.settings.dt)
    try:
        renderer = make_renderer(args.renderer, width, height)
    except RuntimeError as error:   # --renderer ggui without a working Vulkan driver
        raise fem.FemError(f"--renderer {args.renderer}: {error} (--renderer software needs no Vulkan)") from None

    initial = sim.positions()
    camera = fixed_camera(scene.camera, initial, width / height)
    pad = FRAMING_MARGIN * np.ptp(initial, axis=0).max()
    ground_y = scene.effects.ground if scene.effects.ground is not None else initial[:, 1].min() - pad
    coloring = VertexColoring(sim, args.color)
    labels = group_labels(sim.model, initial, camera, width, height) if args.compare else []
    caption = caption_lines(scene, sim, args.compare)

    out.mkdir(parents=True, exist_ok=True)
    timings = {"step": [], "simulation": [], "rendering": [], "writing": []}
    with interrupt_on_sigterm(), VideoWriter(video, args.fps) as writer, \
            tqdm(total=args.frames, unit="frame", desc=scene.name, file=sys.stderr) as progress:
        for index in range(args.frames):
            start = time.perf_counter()
            if index > 0:
                step_ms = [sim.step()["wall_ms"] for _ in range(steps)]
                timings["step"].append(statistics.mean(step_ms))
            simulated = time.perf_counter()
            image = renderer.render(sim.positions(), sim.model.surface, coloring.colors(sim),
                                    camera, ground_y)
            rendered = time.perf_counter()

            lines = caption + [f"t = {sim.t:.2f} s   ({steps} x {sim.settings.dt:g} s steps/frame)"]
            image = coloring.draw_legend(draw_text_overlay(image, lines, corner="bottom-left"))
            for text, centre in labels:
                image = draw_label(image, text, centre)
            write_png(out / FRAME_NAME.format(index), image)
            if writer.active:
                speed = timing_line(timings["step"], 1e3 * (rendered - simulated), renderer.name)
                writer.append(draw_text_overlay(image, lines + [speed], corner="bottom-left"))

            timings["simulation"].append(1e3 * (simulated - start))
            timings["rendering"].append(1e3 * (rendered - simulated))
            timings["writing"].append(1e3 * (time.perf_counter() - rendered))
            progress.update()
    if args.overwrite:
        remove_stale_frames(out, args.frames)

    print(summary(timings, steps, renderer.name))
    where = f"{out / FRAME_NAME.format(0)} .. {FRAME_NAME.format(args.frames - 1)}"
    print(f"wrote {args.frames} frames {where}" + (f" and {video}" if video else ""))
    return 0


# ---------------------------------------------------------------- arguments

def frame_size(text: str, rounded: bool) -> tuple[int, int]:
    """(width, height) in pixels from "WxH"; rounded to multiples of 16 for a video, saying so."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match or min(int(match[1]), int(match[2])) < MACRO_BLOCK:
        raise fem.FemError(f"--size: expected WIDTHxHEIGHT of at least {MACRO_BLOCK}x{MACRO_BLOCK} "
                           f"pixels, e.g. 640x480, got {text!r}")
    width, height = int(match[1]), int(match[2])
    if not rounded:
        return width, height
    w, h = (MACRO_BLOCK * round(n / MACRO_BLOCK) for n in (width, height))
    if (w, h) != (width, height):
        print(f"--size {width}x{height}: video frames must be multiples of {MACRO_BLOCK} pixels; "
              f"using {w}x{h}", file=sys.stderr)
    return w, h


def check_arguments(args, out: Path, video: Path | None):
    """FemError for what cannot work, before any time is spent."""
    if args.frames < 1:
        raise fem.FemError(f"--frames: must be at least 1, got {args.frames}")
    if not args.fps > 0:
        raise fem.FemError(f"--fps: must be > 0, got {args.fps}")
    if args.steps_per_frame is not None and args.steps_per_frame < 1:
        raise fem.FemError(f"--steps-per-frame: must be at least 1, got {args.steps_per_frame}")
    if args.compare and args.method:
        raise fem.FemError(f"--compare runs both methods side by side; drop --{args.method}")
    if out.exists() and not out.is_dir():
        raise fem.FemError(f"--out {out}: is a file, not a folder")
    if video is not None and video.suffix.lower() not in VIDEO_SUFFIXES:
        raise fem.FemError(f"--video {video}: use a .mp4 (H.264) or .gif file name")


def steps_per_frame(requested: int | None, fps: float, dt: float) -> int:
    """Time steps between frames: as requested, else real time at fps (at least 1)."""
    return requested if requested is not None else max(1, round(1.0 / (fps * dt)))


def scene_width(scene) -> float:
    """Extent (m) of the scene's bodies along x."""
    x = np.concatenate([b.mesh.vertices[:, 0] for b in scene.bodies])
    return float(x.max() - x.min())


# ---------------------------------------------------------------- what a frame shows

def fixed_camera(hint: dict | None, positions: np.ndarray, aspect: float) -> Camera:
    """The camera of the whole export: the scene's hint {"eye", "target"} if it
    has one, else one that frames the initial positions (n, 3) with a margin."""
    if hint is None:
        lo, hi = positions.min(axis=0), positions.max(axis=0)
        pad = FRAMING_MARGIN * (hi - lo).max()
        return auto_frame(lo - pad, hi + pad, aspect=aspect)
    distance = np.linalg.norm(np.subtract(hint["eye"], hint["target"]))
    # Clip planes scale with the scene, as auto_frame's do.
    return Camera(eye=hint["eye"], target=hint["target"], near=0.02 * distance, far=20.0 * distance)


def caption_lines(scene, sim, compare: bool) -> list[str]:
    """The overlay's lines that do not change over time: scene, and which method each body uses."""
    if compare:
        count = len(scene.bodies) // 2
        names = [b.name.removesuffix(" (linear)") for b in scene.bodies[:count]]
        return [scene.name, f"left linear, right corotational: {', '.join(names)}"]
    by_method = {}
    for body in sim.scene.bodies:
        by_method.setdefault(body.method, []).append(body.name)
    return [scene.name] + [f"{method}: {', '.join(names)}" for method, names in by_method.items()]


def timing_line(step_ms: list[float], render_ms: float, renderer: str) -> str:
    """Measured speed for the video's overlay: the last frame's ms/step and this frame's rendering."""
    simulation = f"{step_ms[-1]:.1f} ms/step, " if step_ms else ""
    return f"{simulation}{render_ms:.0f} ms/frame to render ({renderer})"


def group_labels(model, positions: np.ndarray, camera: Camera, width: int,
                 height: int) -> list[tuple[str, tuple]]:
    """[(text, (x, y) pixel)]: "linear" over the left copy and "corotational" over the
    right one, above each copy's bounding box in positions (n, 3)."""
    count = len(model.bodies) // 2
    labels = []
    for name, bodies in zip(GROUP_NAMES, (model.bodies[:count], model.bodies[count:])):
        points = np.concatenate([positions[b.vertices] for b in bodies])
        lo, hi = points.min(axis=0), points.max(axis=0)
        pad = FRAMING_MARGIN * (hi - lo).max()
        top = np.array([(lo[0] + hi[0]) / 2, hi[1] + pad, (lo[2] + hi[2]) / 2])
        labels.append((name, project(camera, top, width, height)))
    return labels


def project(camera: Camera, point: np.ndarray, width: int, height: int) -> tuple[float, float]:
    """Pixel (x right, y down) where a world point (3,) appears."""
    clip = camera.view_proj(width / height) @ np.append(point, 1.0)
    return (clip[0] / clip[3] + 1) / 2 * width, (1 - clip[1] / clip[3]) / 2 * height


def draw_label(image: np.ndarray, text: str, centre: tuple) -> np.ndarray:
    """A copy of image (H, W, 3) uint8 with text on a panel centred at pixel centre
    (x, y), moved inside the image where it would stick out."""
    canvas = Image.fromarray(image).convert("RGBA")
    layer = Image.new("RGBA", canvas.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(layer)
    font = ImageFont.load_default(size=max(12, canvas.height // 20))
    padding = font.size // 3
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    box_w, box_h = right - left + 2 * padding, bottom - top + 2 * padding
    x = int(np.clip(centre[0] - box_w / 2, 0, max(canvas.width - box_w, 0)))
    y = int(np.clip(centre[1] - box_h / 2, 0, max(canvas.height - box_h, 0)))
    draw.rounded_rectangle([x, y, x + box_w, y + box_h], radius=padding, fill=PANEL_COLOR)
    draw.text((x + padding - left, y + padding - top), text, font=font, fill=TEXT_COLOR)
    return np.asarray(Image.alpha_composite(canvas, layer).convert("RGB"))


# ---------------------------------------------------------------- files

def write_png(path: Path, image: np.ndarray):
    """Save image (H, W, 3) uint8 as a PNG, under a temporary name until it is complete."""
    with atomic_open(path, "wb") as f:
        Image.fromarray(image).save(f, format="PNG")


def remove_stale_frames(folder: Path, count: int):
    """Delete frames numbered count and above, left by an earlier, longer export, so
    that the folder holds one export's frames only."""
    for path in folder.iterdir():
        match = FRAME_PATTERN.fullmatch(path.name)
        if match and int(match[1]) >= count:
            path.unlink()


class VideoWriter:
    """Appends frames to an MP4 (H.264, yuv420p) or GIF written under a temporary
    name; leaving the `with` block normally renames it into place, an exception removes it.
    With path None it does nothing (active is False)."""

    def __init__(self, path: Path | None, fps: float):
        self.path, self.fps = path, fps
        self.active = path is not None
        self.temporary = atomic_path(path) if self.active else None
        self.writer = None

    def __enter__(self):
        if not self.active:
            return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.suffix.lower() == ".mp4":
            self.writer = imageio.v2.get_writer(
                self.temporary, format="FFMPEG", mode="I", fps=self.fps, codec="libx264",
                pixelformat="yuv420p", quality=8, macro_block_size=MACRO_BLOCK,
                ffmpeg_log_level="error")
        else:
            self.writer = imageio.v3.imopen(self.temporary, "w", plugin="pillow")
        return self

    def append(self, image: np.ndarray):
        """Add one frame, (H, W, 3) uint8, every frame the same size."""
        if self.path.suffix.lower() == ".mp4":
            self.writer.append_data(image)
        else:
            # GIF delays are whole hundredths of a second; loop=0 repeats forever.
            self.writer.write(image, duration=1000.0 / self.fps, loop=0)

    def __exit__(self, kind, error, traceback):
        if not self.active:
            return False
        try:
            self.writer.close()
        finally:
            if kind is None:
                os.replace(self.temporary, self.path)
            else:
                with contextlib.suppress(OSError):
                    os.unlink(self.temporary)
        return False


@contextlib.contextmanager
def interrupt_on_sigterm():
    """Treat SIGTERM (a killed job, a cancelled CI step) like Ctrl-C, so that the
    temporary files are removed on the way out instead of left behind."""
    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def summary(timings: dict, steps: int, renderer: str) -> str:
    """One line of medians over the frames after the first (which compiles the kernels)."""
    def median(key):
        values = timings[key][1:] or timings[key]
        return statistics.median(values) if values else float("nan")

    return (f"{len(timings['rendering'])} frames, {steps} steps/frame: simulation "
            f"{median('simulation'):.1f} ms/frame ({median('step'):.1f} ms/step), rendering "
            f"{median('rendering'):.1f} ms/frame ({renderer}), writing {median('writing'):.1f} ms/frame")
