"""`main.py export`: a scene's frames as PNG files and, optionally, a video, without a display.

    python main.py export epcot --compare --frames 150 --out out/epcot --video out/epcot.mp4

Frame 0 is the initial state; each later frame comes `steps_per_frame` time
steps after the one before. The camera (the scene's camera hint, or framed on
the initial state with room to deform) stays where it is, so frames can be
compared with each other, until a body would leave the picture: then it backs
off to frame everything seen so far, and never comes closer again. The floor is
drawn only for a scene with a ground. --compare shows two panels, like a
report's figure: the linear copy on the left and the corotational copy on the
right, each seen by the same camera. --contact-points marks where bodies touch
(Simulation.contact_points) with dots drawn over the rendered picture, in each panel.

Each frame is written (its PNG, and its video frame) on a thread of its own while the
next one is simulated and rendered (app.video.WriterThread); the timing line at the end
says what the loop spent simulating, rendering and waiting for the writer.

Reproducible pictures: the engine and the software renderer are deterministic
on the CPU, so the PNGs depend only on the scene and the arguments. Their
overlay therefore shows simulated quantities only. Measured speed (ms per
step, ms per frame) changes from run to run: it is drawn on the video's
frames only (a video is re-encoded lossily anyway) and printed at the end.

Videos play at real time: the frame rate is the simulated time between frames
(`--speed 2` plays twice as fast).

Nothing is lost: a non-empty --out folder or an existing --video file is
refused without --overwrite, and every file is written under a temporary
name and renamed when complete. --overwrite replaces frame_00000.png ..
frame_{N-1}.png and the video; nothing else in the folder is touched (older
frames numbered N and above are left, and the summary says so). A folder, or a video,
another export is writing into is refused. An interrupted export (Ctrl-C,
SIGTERM) or one stopped by a full disk keeps the frames written so far and
closes the video on them, and says so.
"""

import contextlib
import os
import re
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

import fem
import scenes
from app import EXIT_INTERRUPTED, device
from app import outputs
from app.commands.simulate import Tally, check_rejected
from app.files import atomic_open, claim, refuse_overwrite
from app.compiling import Compiling, start_done, start_key
from app.progress import Progress
from app.render.camera import Camera, auto_frame
from app.render.colors import VertexColoring
from app.render.factory import make_renderer
from app.render.overlay import draw_labels, draw_points, draw_text_overlay, volume_line
from app.video import MACRO_BLOCK, VIDEO_FPS, VideoFailed, VideoWriter, WriterThread
from fem.errors import SizeLimitError

FRAME_NAME = "frame_{:05d}.png"
FRAME_PATTERN = re.compile(r"frame_(\d{5})\.png")
VIDEO_SUFFIXES = (".mp4", ".gif")
# Frames larger than this a side are refused unless --allow-large: 8K video is 7680 wide,
# and a 100000 x 100000 frame (30 GB) is a typo.
MAX_SIDE = 8192
# More time steps between two frames than this is a slip in --speed or --fps (1e300, 1e-9):
# each frame would take hours. --steps-per-frame asks for any number explicitly.
MAX_STEPS_PER_FRAME = 10_000
# Frame rate aimed at when choosing the steps per frame; the video's own rate then
# makes it play at the requested speed.
TARGET_FPS = 30.0
# Room around the initial state, as a fraction of its largest extent, for bodies to deform into.
FRAMING_MARGIN = 0.25
# From the scene's centre towards an auto-framed camera: in front, to the right and above.
VIEW_DIRECTION = (1.0, 0.6, 1.6)
# Bodies stay inside this part of the picture (normalised device coordinates, -1..1): the
# rest is the edge and the captions' room.
SAFE_AREA = 0.85
# zlib's level for the PNG files: on 640 x 480 epcot frames (2 cores), 1 takes 8 to 9 ms of CPU a
# frame for 38 kB, 3 takes 10 to 11 ms for 36 kB, and Pillow's default 6 takes 18 to 21 ms for 30 kB.
PNG_COMPRESSION = 1
DIVIDER_COLOR = (40, 44, 52)
DIVIDER_WIDTH = 2  # pixels


@dataclass
class Panel:
    """One picture in a frame: some bodies' surface, moved by offset, drawn at a given width.

    faces (k, 3) global vertex ids of the surface triangles; offset (3,) m,
    added to every position; label: text over the picture, or None.
    """

    faces: np.ndarray
    offset: np.ndarray
    width: int
    label: str | None = None


def run(args) -> int:
    """Export frames (and a video) as the parsed command line `args` asks; returns the exit code."""
    width, height = frame_size(args.size, MACRO_BLOCK if args.video else 2 if args.compare else 1,
                               args.allow_large)
    out = Path(args.out)
    video = Path(args.video) if args.video else None
    check_arguments(args, out, video)
    refuse_overwrite(out, args.overwrite)
    if video is None:
        return simulate_and_write(args, out, video, width, height)
    refuse_overwrite(video, args.overwrite)
    outputs.remove_stale_temporaries(video.parent, video.name)     # a killed export's video
    claimed = claim(video, "--video")
    try:
        return simulate_and_write(args, out, video, width, height)
    finally:
        with contextlib.suppress(FileNotFoundError):       # gone already where the video was put in place
            os.unlink(claimed)


def simulate_and_write(args, out: Path, video: Path | None, width: int, height: int) -> int:
    """Build the simulation and the view, then write the frames into the locked folder out."""
    device.start(args)
    with Compiling(Path(args.scene).stem, start_key(args)):     # says so until the first stepped frame
        scene = scenes.load_scene(args.scene, overrides=args.set, contact=getattr(args, "contact", False))
        if args.contact_points and scene.effects.contact is None:
            raise fem.FemError(f"--contact-points: {scene.name} has no contact between bodies to show; add "
                               "--contact, or `[effects] contact = { distance = 0.01 }` to the scene")
        sim = fem.Simulation(scene.side_by_side() if args.compare else scene, method=args.method,
                             solver=args.solver, dt=args.dt, tolerance=args.tol,
                             max_iterations=args.max_iters, step=args.step,
                             integrator=args.integrator)
        steps = steps_per_frame(args.steps_per_frame, args.fps or TARGET_FPS, args.speed, sim.settings.dt)
        fps = args.fps or video_rate(steps, sim.settings.dt, args.speed)
        if video is not None:
            check_video_rate(video, fps, args.fps is not None)
        view = View(sim, scene, args.compare, args.color, args.renderer, width, height, args.contact_points)

        out.mkdir(parents=True, exist_ok=True)
        with outputs.FolderLock(out) as lock:
            outputs.remove_stale_temporaries(out)
            refuse_overwrite(out, args.overwrite)      # again: another run may have written meanwhile
            return write_frames(args, sim, scene, view, lock, video, steps, fps)


def write_frames(args, sim, scene, view, lock, video, steps, fps) -> int:
    """Step and render every frame, and write it (PNG and video) on a thread of its own while
    the next one is made, into the folder `lock` holds."""
    out = lock.folder
    timings = {"step": [], "simulation": [], "rendering": []}
    steps_run = Tally()
    written = 0                 # complete PNG files
    writer = VideoWriter(video, fps, args.overwrite)

    def write(index, picture, lines, speed):
        # The PNG, the video's frame and the count move together (on the writer's thread, which no
        # signal interrupts): an interruption leaves as many frames in the video as PNG files.
        nonlocal written
        if lock.removed():
            raise fem.FemError(frames_kept(lock, written))
        write_png(out / FRAME_NAME.format(index), view.annotated(picture, lines),
                  f"kept the {index} complete frames before it")
        written = index + 1
        if writer.active:
            writer.append(view.annotated(picture, lines + [speed]))

    try:
        with writer, WriterThread(write) as frames, Progress(args.frames, "frame", scene.name) as progress:
            for index in range(args.frames):
                start = time.perf_counter()
                if index > 0:
                    infos = [sim.step() for _ in range(steps)]
                    steps_run += infos
                    timings["step"].append(statistics.mean(info["wall_ms"] for info in infos))
                simulated = time.perf_counter()
                picture, lines = view.picture(sim), view.lines(sim, steps)
                rendered = time.perf_counter()
                speed = timing_line(timings["step"], 1e3 * (rendered - simulated), view.renderer.name)
                frames.put(index, picture, lines, speed)
                if index == 1:
                    start_done()
                timings["simulation"].append(1e3 * (simulated - start))
                timings["rendering"].append(1e3 * (rendered - simulated))
                progress.update()
    except KeyboardInterrupt:
        kept = (f"kept the {written} complete frames {out / FRAME_NAME.format(0)} .. "
                f"{FRAME_NAME.format(written - 1)}" if written else "no frame was complete")
        also = f" and {video} with {writer.frames} frames" if writer.active and writer.frames else ""
        older = older_frames(out, written)
        names = f"{older[0]} is" if len(older) == 1 else f"{older[0]} .. {older[-1]} are" if older else ""
        earlier = f"; {names} older, not from this export" if older else ""
        print(f"interrupted at frame {written} of {args.frames}: {kept}{also}{earlier}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except VideoFailed as error:
        raise fem.FemError(f"{error}; {frames_kept(lock, written)}") from None
    except fem.FemError as error:           # a frame could not be written: the video closed on the others
        if lock.removed():                  # then what write_png says was kept went with the folder
            error = frames_kept(lock, written)
        also = f"; {video} holds them ({writer.frames} frames)" if writer.placed else ""
        raise fem.FemError(f"{error}{also}") from None
    print(summary(timings, frames, steps, view.renderer.name))
    if video is not None:
        print(f"the video plays at {fps:.4g} frames per second: "
              f"{fps * steps * sim.settings.dt:.3g}x real time")
    where = f"{out / FRAME_NAME.format(0)} .. {FRAME_NAME.format(args.frames - 1)}"
    print(f"wrote {args.frames} frames {where}" + (f" and {video}" if video else ""))
    older = older_frames(out, args.frames)
    if older:
        print(f"note: {out} also holds {len(older)} older frames ({older[0]} ..), not from this export; "
              "they were left as they were", file=sys.stderr)
    return check_rejected(steps_run, sim.settings.dt)


class View:
    """What every frame shows and from where: panels, renderer, fixed camera and floor, colours, captions.

    sim: the running simulation (of scene.side_by_side() when compare);
    scene: the scene as loaded, for its camera hint and ground;
    color: a VertexColoring mode; renderer: "auto", "ggui" or "software";
    width, height: of the whole frame, pixels; contact_points: mark the simulation's contact points.
    """

    def __init__(self, sim, scene, compare: bool, color: str, renderer: str, width: int, height: int,
                 contact_points: bool = False):
        self.panels = compare_panels(sim, width) if compare else [
            Panel(sim.model.surface, np.zeros(3), width)]
        try:
            self.renderer = make_renderer(renderer, self.panels[0].width, height)
        except RuntimeError as error:   # --renderer ggui without a working Vulkan driver
            raise fem.FemError(f"--renderer {renderer}: {error} "
                               "(--renderer software needs no Vulkan)") from None
        # Framed on the first panel's bodies: the others are copies of them, moved onto them.
        initial = sim.positions()[np.unique(self.panels[0].faces)]
        self.aspect = self.panels[0].width / height
        self.camera = (auto_framed(initial, self.aspect, scene.camera) if compare or scene.camera is None
                       else hinted(scene.camera))
        self.framed = (initial.min(axis=0), initial.max(axis=0))   # what the camera holds in view
        self.ground_y = scene.effects.ground                        # None: no floor
        self.coloring = VertexColoring(sim, color, copies=2 if compare else 1)
        self.contact_points = contact_points
        self.caption = [scene.name]                        # the lines every frame starts with
        # Each body's name as the scene gives it: a --compare copy's is the same as its original's.
        self.names = [b.name for b in scene.bodies] * (2 if compare else 1)
        # Over the sky, or over the floor where the panels' labels take the top.
        self.corner = "bottom-left" if compare else "top-left"

    def picture(self, sim) -> np.ndarray:
        """The simulation now, (H, W, 3) uint8: every panel, labels and the colour legend."""
        positions, colors = sim.positions(), self.coloring.colors(sim)
        seen = [positions[np.unique(p.faces)] for p in self.panels]
        shown = np.concatenate([points + p.offset for points, p in zip(seen, self.panels)])
        self.camera, self.framed = widened(self.camera, self.framed, shown, self.aspect)
        pictures = [self.renderer.render(positions + p.offset, p.faces, colors, self.camera,
                                         self.ground_y) for p in self.panels]
        if self.contact_points:
            pictures = [draw_points(picture, points + p.offset, self.camera) for picture, points, p
                        in zip(pictures, by_panel(sim.contact_points, seen), self.panels)]
        return self.coloring.draw_legend(join_panels(pictures, self.panels))

    def lines(self, sim, steps: int) -> list[str]:
        """The overlay's lines for the simulation now, `steps` time steps after the frame before."""
        bodies = zip(self.names, (b.method for b in sim.model.bodies), sim.stats()["volume_ratio"])
        return self.caption + [volume_line(list(bodies)), f"t = {sim.t:.2f} s ({steps} steps/frame)"]

    def annotated(self, picture: np.ndarray, lines: list[str]) -> np.ndarray:
        """A copy of picture with lines of text in the overlay's corner."""
        return draw_text_overlay(picture, lines, self.corner)


# ---------------------------------------------------------------- arguments

def frame_size(text: str, multiple: int, allow_large: bool = False) -> tuple[int, int]:
    """(width, height) in pixels from "WxH", rounded to a multiple (16 for a video,
    2 for two equal panels), saying so when that changes them; at most MAX_SIDE a side
    unless allow_large."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match or min(int(match[1]), int(match[2])) < MACRO_BLOCK:
        raise fem.FemError(f"--size: expected WIDTHxHEIGHT of at least {MACRO_BLOCK}x{MACRO_BLOCK} "
                           f"pixels, e.g. 640x480, got {text!r}")
    width, height = int(match[1]), int(match[2])
    if max(width, height) > MAX_SIDE and not allow_large:
        raise SizeLimitError(f"--size {width}x{height}: more than {MAX_SIDE} pixels a side, the limit "
                             f"(one frame would take {3 * width * height / 1e9:.1f} GB)")
    w, h = (multiple * round(n / multiple) for n in (width, height))
    if (w, h) != (width, height):
        print(f"--size {width}x{height}: frames must be multiples of {multiple} pixels here; "
              f"using {w}x{h}", file=sys.stderr)
    return w, h


def check_arguments(args, out: Path, video: Path | None):
    """FemError for what cannot work, before any time is spent (main.py's parser
    has already checked each number on its own)."""
    if args.compare and args.method:
        raise fem.FemError(f"--compare runs both methods side by side; drop --{args.method}")
    if out.exists() and not out.is_dir():
        raise fem.FemError(f"--out {out}: is a file, not a folder")
    if video is not None and video.suffix.lower() not in VIDEO_SUFFIXES:
        raise fem.FemError(f"--video {video}: use a .mp4 (H.264) or .gif file name")
    if video is not None and outputs.is_special(video):
        raise fem.FemError(f"--video {video}: not a regular file (a device or a pipe); give a file name")
    if video is not None and video.absolute() == out.absolute():
        raise fem.FemError(f"--video {video}: is also the --out folder; give the video another name")


def check_video_rate(video: Path, fps: float, asked: bool):
    """FemError unless a video can play at fps frames per second (--fps if asked, else what
    --speed makes it)."""
    low, high = VIDEO_FPS[video.suffix.lower()]
    if not low <= fps <= high:
        why = f"--fps {fps:g}" if asked else f"--speed: the video would play at {fps:.3g} frames per second"
        raise fem.FemError(f"{why}; a {video.suffix.lower()} video plays at {low:g} to {high:g} frames "
                           "per second (--fps, --speed and --steps-per-frame set it)")


def steps_per_frame(requested: int | None, fps: float, speed: float, dt: float) -> int:
    """Time steps between frames: as requested, else the number that shows `speed` seconds
    of simulated time per second of video at about fps frames per second (at least 1), at most
    MAX_STEPS_PER_FRAME."""
    if requested is not None:
        return requested
    steps = speed / (fps * dt)
    if not steps <= MAX_STEPS_PER_FRAME:
        raise fem.FemError(f"--speed {speed:g} at {fps:g} frames per second and dt {dt:g} s needs {steps:.3g} "
                           f"steps per frame, more than {MAX_STEPS_PER_FRAME:,}: lower --speed, raise --fps, "
                           "or give --steps-per-frame")
    return max(1, round(steps))


def video_rate(steps: int, dt: float, speed: float) -> float:
    """Frames per second at which frames `steps` time steps of dt seconds apart play at
    `speed` times real time."""
    return speed / (steps * dt)


# ---------------------------------------------------------------- what a frame shows

def compare_panels(sim, width: int) -> list[Panel]:
    """Two half-width panels: the linear copy on the left, the corotational copy on the
    right moved back onto it, so that one camera shows both from the very same view."""
    bodies, count = sim.model.bodies, len(sim.model.bodies) // 2
    scene_bodies = sim.scene.bodies
    # Scene.side_by_side: body count + i is body i shifted along x.
    shift = scene_bodies[count].mesh.vertices[0] - scene_bodies[0].mesh.vertices[0]
    left = np.concatenate([b.surface for b in bodies[:count]])
    right = np.concatenate([b.surface for b in bodies[count:]])
    return [Panel(left, np.zeros(3), width // 2, "linear"),
            Panel(right, -shift, width // 2, "corotational")]


def by_panel(points: np.ndarray, seen: list[np.ndarray]) -> list[np.ndarray]:
    """points (k, 3) split by panel: each goes to the panel whose vertices (seen[i], (n_i, 3))
    have the nearest bounding box (a contact point lies between two bodies of one copy)."""
    gaps = [np.linalg.norm(np.maximum(0, np.maximum(v.min(axis=0) - points, points - v.max(axis=0))), axis=1)
            for v in seen]
    owner = np.argmin(gaps, axis=0)
    return [points[owner == k] for k in range(len(seen))]


def auto_framed(positions: np.ndarray, aspect: float, hint: dict | None) -> Camera:
    """A camera that frames positions (n, 3) with a margin, from the scene's hint's
    direction (eye - target) if there is one."""
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    pad = FRAMING_MARGIN * (hi - lo).max()
    direction = VIEW_DIRECTION if hint is None else np.subtract(hint["eye"], hint["target"])
    return auto_frame(lo - pad, hi + pad, direction=direction, aspect=aspect)


def widened(camera: Camera, framed, points: np.ndarray, aspect: float):
    """(camera, framed): unchanged while every point (n, 3) projects inside SAFE_AREA; else a
    camera from the same direction framing the box framed = (lo, hi) grown to hold the points."""
    clip = np.c_[points, np.ones(len(points))] @ camera.view_proj(aspect).T
    inside = (clip[:, 3] > 0) & (np.abs(clip[:, :2]) <= SAFE_AREA * clip[:, 3:4]).all(axis=1)
    if inside.all():
        return camera, framed
    lo, hi = np.minimum(framed[0], points.min(axis=0)), np.maximum(framed[1], points.max(axis=0))
    return auto_framed(np.array([lo, hi]), aspect, {"eye": camera.eye, "target": camera.target}), (lo, hi)


def hinted(hint: dict) -> Camera:
    """The camera the scene asks for: {"eye", "target"} (3,) each, in metres."""
    distance = np.linalg.norm(np.subtract(hint["eye"], hint["target"]))
    # Clip planes scale with the scene, as auto_frame's do.
    return Camera(eye=hint["eye"], target=hint["target"], near=0.02 * distance, far=20.0 * distance)


def join_panels(pictures: list[np.ndarray], panels: list[Panel]) -> np.ndarray:
    """The panels' pictures (H, w, 3) side by side, with a divider line and labels."""
    if len(pictures) == 1:
        return pictures[0]
    image = np.concatenate(pictures, axis=1)
    edges = np.cumsum([p.width for p in panels])[:-1]
    for edge in edges:
        image[:, edge - DIVIDER_WIDTH // 2: edge + DIVIDER_WIDTH // 2] = DIVIDER_COLOR
    centres = np.concatenate([[0], edges]) + np.array([p.width for p in panels]) / 2
    return draw_labels(image, [(p.label, x) for p, x in zip(panels, centres)])


def timing_line(step_ms: list[float], render_ms: float, renderer: str) -> str:
    """Measured speed for the video's overlay: the last frame's ms/step and this frame's rendering."""
    simulation = f"{step_ms[-1]:.1f} ms/step, " if step_ms else ""
    return f"{simulation}{render_ms:.0f} ms/frame to render ({renderer})"


# ---------------------------------------------------------------- files

def write_png(path: Path, image: np.ndarray, kept: str = ""):
    """Save image (H, W, 3) uint8 as a PNG, under a temporary name until it is complete;
    a full disk is a FemError naming the frame and what was `kept`."""
    try:
        with atomic_open(path, "wb", make_folder=False) as f:     # a removed --out stays removed
            Image.fromarray(image).save(f, format="PNG", compress_level=PNG_COMPRESSION)
    except fem.FemError as error:
        raise fem.FemError(f"{error}; {kept}" if kept else str(error)) from None


def frames_kept(lock: outputs.FolderLock, written: int) -> str:
    """What is left of the `written` complete frames in the folder `lock` holds, for a message."""
    if lock.removed():
        return (f"--out {lock.folder} was removed while this run wrote into it; the {written} frames "
                "written before went with it")
    return f"kept the {written} complete frames in {lock.folder}" if written else "no frame was complete"


def older_frames(folder: Path, count: int) -> list[str]:
    """Names of the frames numbered count and above in folder (an earlier, longer export's,
    or the user's own): --overwrite leaves them, and the summary says so."""
    names = [path.name for path in folder.iterdir() if (match := FRAME_PATTERN.fullmatch(path.name))
             and int(match[1]) >= count]
    return sorted(names)


def summary(timings: dict, frames: WriterThread, steps: int, renderer: str) -> str:
    """One line of medians over the frames after the first (which compiles the kernels): what the
    loop spent simulating, rendering and waiting for the writer, and the writer's own time, spent
    beside the loop."""
    def median(values):
        values = values[1:] or values
        return statistics.median(values) if values else float("nan")

    return (f"{len(timings['rendering'])} frames, {steps} steps/frame: simulation "
            f"{median(timings['simulation']):.1f} ms/frame ({median(timings['step']):.1f} ms/step), rendering "
            f"{median(timings['rendering']):.1f} ms/frame ({renderer}), waiting for the writer "
            f"{median(frames.waited_ms):.1f} ms/frame (it wrote each frame in {median(frames.busy_ms):.1f} ms, "
            "beside the loop)")
