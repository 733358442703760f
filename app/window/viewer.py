"""The interactive window of `main.py view` (Taichi GGUI).

Poke a body with the mouse and watch linear FEM inflate as it turns while
corotational FEM keeps its volume. The window only reads the engine's state
and talks to it through its public calls: `apply_impulse`, `set_method`,
`set_material`, `settings`, `reset`.

One frame: read input -> step the simulation (real time when it keeps up) ->
draw the bodies, the floor and the panel -> write a stats line.

While a scene starts, Taichi compiles its kernels for seconds (a minute on a cold cache). Between
two kernels the window shows the picture at rest and "compiling kernels, 12 of 40", and keeps the
clicks and keys it reads for the first frame that steps (`between_kernels`).

The Viewer's input handling is app/window/controls.py, its panel app/window/panel.py.
"""

import json
import sys
import time
from pathlib import Path

import numpy as np
import taichi as ti

import fem
import scenes
from app import outputs
from app.files import atomic_open, atomic_path, numbered_path
from app.render.camera import Camera, auto_frame
from app.render.colors import VertexColoring
from app.render.frame import background, build_frame
from app.render.ggui import _quiet_taichi, _to_ggui_layout
from app.render.overlay import draw_labels, draw_points
from app.render.software import SoftwareRenderer, to_window_layout
from app.window import orbit
from app.window.compiling import COMPILING_FRAME_SECONDS, CompilingFrames
from app.window.controls import DRAG_PIXELS, MARKER_SECONDS, Controls
from app.window.panel import Panel, panel_width
from fem.scene import PRECONDITIONERS

MAX_STEPS_PER_FRAME = 8
VIDEO_FPS = 30
MARKER_COLOR = (1.0, 0.85, 0.1)


class Viewer(Controls, Panel, CompilingFrames):
    def __init__(self, args, width, height):
        self.args, self.width, self.height = args, width, height
        names = list(scenes.builtin_scenes())
        self.scene_refs = names if args.scene in names else [args.scene] + names
        try:
            # At the screen's top-left corner (Taichi's default is 100 px in): a window the screen's
            # size then fits it where no window manager places it, as under Xvfb.
            self.window = ti.ui.Window("softfem", (width, height), vsync=False, pos=(0, 0))
        # Whatever stops it (no Vulkan driver, GLFW without a display) is one line, not a traceback.
        except Exception as e:
            raise fem.FemError(f"view: cannot open the window: {e}") from None
        self.canvas = self.window.get_canvas()
        self.scene3d = self.window.get_scene()
        self.ggui_camera = ti.ui.Camera()
        self.gui = self.window.get_gui()
        self.backdrop = ti.Vector.field(3, ti.f32, (width, height))
        self.backdrop.from_numpy(_to_ggui_layout(background(width, height)))
        # The bodies are rasterised by Taichi kernels and shown as the canvas's image: GGUI's own
        # 3D scene (Taichi 1.7) keeps a few hundred kB per mesh drawn, every frame, until the
        # process ends (gigabytes in an hour; its particles too, about 120 kB a frame). Only the
        # click marker goes through it; the contact points (t) are drawn into the picture.
        self.rasteriser = SoftwareRenderer(width, height, smooth=True)
        self.picture = ti.Vector.field(3, ti.f32, (width, height))
        self.marker_point = ti.Vector.field(3, ti.f32, 1)
        self.marker_arrow = ti.Vector.field(3, ti.f32, 16)
        self.sim = self.stats = None
        self.paused = self.show_help = self.show_contacts = False
        self.coloring = None
        self.events, self.frame = [], 0
        self.frame_seconds, self.render_ms, self.steps_last_frame = None, None, 0    # None: not measured yet
        self.press, self.marker, self.marker_until = None, None, 0.0
        self.drag_origin = None
        self.waiting = []                # input read while kernels compiled (controls.Input)
        self.compiling = None            # app.compiling.Compiling while a scene starts
        self.busy = False                # drawing a frame: between_kernels stays out
        self.next_compiling_frame = 0.0  # time.perf_counter(), s
        self.scene_due = None            # a scene chosen in the panel, loaded at the next frame
        self.screenshot_due = False
        self.video, self.video_path, self.video_start, self.video_frames = None, None, 0.0, 0
        self.message = ""
        self.load(args.scene)

    # ------------------------------------------------------------ scenes

    def load(self, ref):
        """Build the simulation of a scene; its first frame shows it at rest, then `warm_up`
        compiles every kernel its steps need (a scene of the same kind: none)."""
        self.start_compiling(ref)
        self.sim = self.stats = None  # the old scene's fields go back to the pool: a scene of the same kind compiles nothing
        self.show_compiling()
        args = self.args
        scene = scenes.load_scene(ref, overrides=args.set if Path(str(ref)).suffix != ".txt" else None,
                                   contact=getattr(args, "contact", False))
        if args.compare:
            # A gap as wide as the scene, so that a linear copy growing as it turns stays clear of its twin.
            width = np.ptp(np.concatenate([b.mesh.vertices for b in scene.bodies])[:, 0])
            scene = scene.side_by_side(gap=max(0.5, float(width)))
        sim = fem.Simulation(scene, method=None if args.compare else args.method, solver=args.solver,
                             dt=args.dt, tolerance=args.tol, max_iterations=args.max_iters, step=args.step,
                             integrator=args.integrator)
        self.warm_up_due = True          # after the scene's first frame is shown (loop)
        self.sim, self.ref = sim, ref
        self.scene_methods = self.methods()        # what `r` restores
        model = sim.model
        self.body_starts = np.array([b.vertices.start for b in model.bodies])
        self.twins = len(model.bodies) // 2 if args.compare else 0
        self.x = sim.positions()
        lo, hi = self.x.min(axis=0), self.x.max(axis=0)
        self.size = float(np.linalg.norm(hi - lo))
        self.strength = 1.0 * self.size        # m/s at the hit point
        self.radius = 0.2 * self.size          # m
        self.material_body = 0
        self.material_edit = None
        self.set_color_mode(self.coloring.mode if self.coloring else "body")
        self.reset_view()
        self.labels = copy_labels(self.x, int(self.body_starts[self.twins]), self.camera,
                                  self.width / self.height) if self.twins else []
        self.draw_copy_labels()
        self.stats = sim.stats()
        self.events.append({"type": "scene", "scene": str(ref), "name": scene.name,
                            "methods": self.methods()})

    def reset_view(self):
        """Frame the bodies, looking along the scene's own camera direction when it has one,
        and slide them left so the panel does not cover them."""
        self.camera = initial_camera(self.x, self.sim.scene.camera, self.width, self.height,
                                     compare=self.args.compare)

    def methods(self):
        return [b.method for b in self.sim.model.bodies]

    # ------------------------------------------------------------ main loop

    @property
    def fps(self):
        """Frames per second, from a running mean of the frame time; None before a frame was timed."""
        return None if self.frame_seconds is None else 1.0 / max(self.frame_seconds, 1e-6)

    def loop(self, stats_file):
        last = None         # when the frame before began; None: no frame to time yet
        while self.window.running:
            if self.scene_due is not None:
                self.switch_scene(self.scene_due)
                last, self.frame_seconds = None, None
            now = time.perf_counter()
            frame_seconds, last = (None if last is None else now - last), now
            if frame_seconds is not None:       # a running mean, which a single slow frame barely moves
                self.frame_seconds = frame_seconds if self.frame_seconds is None else \
                    0.9 * self.frame_seconds + 0.1 * frame_seconds
            self.handle_keys()
            if not self.warm_up_due:
                self.handle_mouse()
            if not self.window.running:
                break
            if not self.paused and not self.warm_up_due:
                self.advance(frame_seconds)
            self.stats = self.sim.stats()
            self.draw()
            if self.compiling is not None and not self.warm_up_due:
                self.end_compiling()         # the frame after warm_up: its steps and stats are compiled
            if stats_file:
                row = dict(self.stats, frame=self.frame, events=self.events)
                stats_file.write(json.dumps(row) + "\n")
                stats_file.flush()   # a reader (or a test) can follow the frames as they come
            self.events = []
            self.frame += 1
            if self.warm_up_due:         # the scene is on screen: now compile what its steps need
                warm_up(self.sim)
                # The frame that compiled is no frame to time, nor the first one after it, which
                # follows the compiling at once.
                self.warm_up_due, last, self.frame_seconds = False, None, None
        self.stop_video()

    def advance(self, frame_seconds):
        """Real time when the simulation keeps up (as many steps as the frame took), else one step
        (also when the frame was not timed: frame_seconds None)."""
        dt = self.sim.settings.dt
        step_seconds = self.sim.last.get("wall_ms", 0.0) / 1e3
        steps = 1
        if frame_seconds is not None and step_seconds < dt:
            steps = int(np.clip(round(frame_seconds / dt), 1, MAX_STEPS_PER_FRAME))
        for _ in range(steps):
            self.sim.step()
        self.steps_last_frame = steps

    # ------------------------------------------------------------ actions

    def reset(self):
        """Start the scene again, with each body's own method (as loaded), whatever `c` changed."""
        self.sim.reset()
        self.events.append({"type": "reset"})
        if self.methods() != self.scene_methods:
            self.set_methods(self.scene_methods)

    def toggle_corotation(self):
        """Every body corotational, or (when they all are already) every body linear."""
        all_corotational = all(m == "corotational" for m in self.methods())
        self.set_methods(["linear" if all_corotational else "corotational"] * len(self.methods()))

    def toggle_contact_points(self):
        """Show or hide where bodies touch (Simulation.contact_points; none without contact)."""
        self.show_contacts = not self.show_contacts
        if self.show_contacts and self.sim.scene.effects.contact is None:
            self.message = "no contact in this scene (--contact)"
        self.events.append({"type": "contact_points", "shown": self.show_contacts})

    def next_preconditioner(self):
        """PCG's preconditioner, in turn: auto, two-level, block Jacobi (the engine reads it next step)."""
        settings = self.sim.settings
        settings.preconditioner = PRECONDITIONERS[(PRECONDITIONERS.index(settings.preconditioner) + 1)
                                                  % len(PRECONDITIONERS)]
        self.events.append({"type": "preconditioner", "preconditioner": settings.preconditioner})

    def set_methods(self, methods):
        for body, method in enumerate(methods):
            if method != self.sim.model.bodies[body].method:
                self.sim.set_method(method, body)
        self.events.append({"type": "methods", "methods": self.methods()})
        self.draw_copy_labels()

    def toggle_video(self):
        if self.video is not None:
            self.stop_video()
            return
        import imageio.v2 as imageio
        self.video_path = numbered_path(self.args.out, f"softfem-{Path(str(self.ref)).stem}", ".mp4")
        self.video_path.parent.mkdir(parents=True, exist_ok=True)
        self.video = imageio.get_writer(atomic_path(self.video_path), fps=VIDEO_FPS, codec="libx264",
                                        macro_block_size=16, quality=7)
        self.video_start, self.video_frames = time.perf_counter(), 0
        self.message = f"recording {self.video_path}"
        print(self.message, file=sys.stderr)
        self.events.append({"type": "video", "recording": True, "path": str(self.video_path)})

    def stop_video(self):
        if self.video is None:
            return
        self.video.close()
        outputs.put_in_place(atomic_path(self.video_path), self.video_path, overwrite=False)
        self.message = f"saved {self.video_path}"
        print(self.message, file=sys.stderr)
        self.events.append({"type": "video", "recording": False, "path": str(self.video_path)})
        self.video = None

    def record(self, image):
        """Add the window's image to the recording as often as it stays on screen at VIDEO_FPS,
        so the video plays at the speed it was seen (a slow frame repeats, a fast one may drop)."""
        due = int((time.perf_counter() - self.video_start) * VIDEO_FPS) + 1
        for _ in range(due - self.video_frames):
            self.video.append_data(image)
        self.video_frames = max(self.video_frames, due)

    # ------------------------------------------------------------ drawing

    def set_color_mode(self, mode):
        """Colour by "body", "volume" or "strain", with the exporter's scales (app.render.colors)."""
        self.coloring = VertexColoring(self.sim, mode, copies=2 if self.twins else 1)

    def draw(self):
        start = time.perf_counter()
        self.busy = True
        self.x = self.sim.positions()
        frame = build_frame(self.x, self.sim.model.surface, self.coloring.colors(self.sim), self.camera,
                            ground_y=self.ground_y(), smooth=True)
        self.rasteriser.draw(frame, self.camera)
        if self.show_contacts and len(self.sim.contact_points):
            # As the export draws them, over the bodies (app/render/overlay.py).
            self.rasteriser.image.from_numpy(draw_points(self.rasteriser.image.to_numpy(),
                                                         self.sim.contact_points, self.camera))
        to_window_layout(self.rasteriser.image, self.picture)
        with _quiet_taichi():
            self.canvas.set_image(self.picture)
            if self.draw_marker():               # GGUI's 3D scene only while a marker shows
                cam, g = self.camera, self.ggui_camera
                g.position(*cam.eye)
                g.lookat(*cam.target)
                g.up(*cam.up)
                g.fov(cam.fov_deg)
                g.z_near(cam.near)
                g.z_far(cam.far)
                self.scene3d.set_camera(g)
                self.scene3d.ambient_light((1.0,) * 3)
                self.canvas.scene(self.scene3d)
            self.draw_panel()
            if self.show_help:
                self.draw_help()
            if self.video is not None or self.screenshot_due:
                self.capture()
            self.window.show()
        self.busy = False
        end = time.perf_counter()
        self.next_compiling_frame = end + COMPILING_FRAME_SECONDS
        self.render_ms = 1e3 * (end - start)

    def ground_y(self):
        """The ground's height, m, or None without a ground: then no floor is drawn."""
        return self.sim.scene.effects.ground

    def draw_copy_labels(self):
        """In compare mode, "linear" and "corotational" at the top of the view, over where the
        copies start, as the export labels them: drawn into the backdrop behind the bodies, so
        they cost a frame nothing (at the top, a growing copy does not cover them). Called again
        when the bodies' methods change."""
        image = np.round(255 * background(self.width, self.height)).astype(np.uint8)
        if self.twins:
            methods = copy_methods(self.methods(), self.twins)
            image = draw_labels(image, [(label, x * self.width) for label, (_, x) in zip(methods, self.labels)])
        self.rasteriser.backdrop.from_numpy(image.astype(np.float32) / 255)

    def draw_marker(self):
        """The last click's hit point and its push as an arrow, or the drag in progress, into the
        3D scene; returns whether there is one to draw (drawn over the bodies)."""
        if self.press is not None and self.press.hit is not None:
            drag = self.cursor() - self.press.pixel
            if np.linalg.norm(drag) > DRAG_PIXELS:
                right, true_up, _ = self.camera.basis()
                direction = drag[0] * right - drag[1] * true_up
                strength = self.strength * min(np.linalg.norm(drag) / (0.2 * self.height), 4.0)
                # From the hit point towards the mouse, as the push will go.
                self.marker = (self.press.hit.point, strength * direction / np.linalg.norm(direction), "tail")
                self.marker_until = time.perf_counter() + MARKER_SECONDS
        if self.marker is None or time.perf_counter() > self.marker_until:
            return False
        point, delta_v, end = self.marker
        self.marker_point.from_numpy(point[None].astype(np.float32))
        self.scene3d.particles(self.marker_point, radius=0.025 * self.size, color=MARKER_COLOR)
        # The arrow as a row of beads: GGUI's lines are one pixel wide on some drivers.
        self.marker_arrow.from_numpy(arrow_beads(point, delta_v, 0.4 * self.size / max(self.strength, 1e-9),
                                                 self.marker_arrow.shape[0], end).astype(np.float32))
        self.scene3d.particles(self.marker_arrow, radius=0.012 * self.size, color=MARKER_COLOR)
        return True

    def capture(self):
        rgba = self.window.get_image_buffer_as_numpy()
        image = np.round(rgba[:, ::-1, :3].transpose(1, 0, 2) * 255).astype(np.uint8)
        if self.video is not None:
            self.record(image)
        if self.screenshot_due:
            from PIL import Image
            path = numbered_path(self.args.out, f"softfem-{Path(str(self.ref)).stem}", ".png")
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_open(path, "wb") as f:
                Image.fromarray(image).save(f, format="PNG")
            self.message = f"saved {path}"
            print(self.message, file=sys.stderr)
            self.events.append({"type": "screenshot", "path": str(path)})
            self.screenshot_due = False

    def switch_scene(self, ref):
        self.scene_due = None
        self.stop_video()
        self.load(ref)


def initial_camera(positions, scene_camera, width, height, compare=False) -> Camera:
    """A camera framing positions (n, 3) in the part of a width x height window left of the
    panel, looking along the scene's camera direction ({"eye", "target"} or None); in
    compare mode from nearly straight ahead, so that neither copy hides the other."""
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    direction = np.subtract(scene_camera["eye"], scene_camera["target"]) if scene_camera else (1.0, 0.6, 1.6)
    if compare:
        horizontal = np.hypot(direction[0], direction[2])
        direction = (0.2 * horizontal, direction[1], horizontal)
    panel = panel_width(width)
    camera = auto_frame(lo, hi, direction=direction, aspect=width * (1 - panel) / height)
    # Sliding the camera right moves the scene left, to the middle of the uncovered part.
    return orbit.pan(camera, -panel * width / 2, 0.0, height)


def copy_labels(positions, split, camera, aspect):
    """[("linear", x), ("corotational", x)]: where to label the two copies of --compare, as
    fractions of the window's width from its left edge: over the middle of each copy as seen.
    positions (n, 3): the linear copies' vertices come before `split`."""
    labels = []
    for label, points in (("linear", positions[:split]), ("corotational", positions[split:])):
        lo, hi = points.min(axis=0), points.max(axis=0)
        corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        clip = corners @ camera.view_proj(aspect).T
        x = (clip[:, 0] / clip[:, 3] + 1) / 2
        labels.append((label, float(np.clip((x.min() + x.max()) / 2, 0, 1))))
    return labels


def warm_up(sim):
    """Compile every kernel the window may need (both methods, the stats) now,
    so that toggling corotation later does not stall a frame; then start over."""
    methods = [b.method for b in sim.model.bodies]
    for method in ("corotational", "linear"):
        sim.set_method(method)
        sim.step()
    sim.stats()
    sim.tet_values()
    for body, method in enumerate(methods):
        sim.set_method(method, body)
    sim.reset()


def arrow_beads(point, delta_v, metres_per_mps, count, end="tip"):
    """count points (count, 3) from the arrow's tail to its tip: an arrow along delta_v, the
    way the push goes, |delta_v| * metres_per_mps long, with its tip at `point` (end "tip": a
    click, pushing into the body) or its tail there (end "tail": a drag, towards the mouse)."""
    length = np.linalg.norm(delta_v) * metres_per_mps
    direction = delta_v / max(np.linalg.norm(delta_v), 1e-12)
    tail = point - length * direction if end == "tip" else point
    return tail + length * np.linspace(0.0, 1.0, count)[:, None] * direction


def copy_methods(methods, twins):
    """The labels of the two copies of --compare as their bodies' methods are now, e.g.
    ["linear", "corotational"], or ["linear", "linear"] after `c` made every body linear."""
    def label(copy):
        return copy[0] if len(set(copy)) == 1 else "mixed"

    return [label(methods[:twins]), label(methods[twins:])]

