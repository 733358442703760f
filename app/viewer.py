"""`main.py view`: the interactive window (Taichi GGUI).

Poke a body with the mouse and watch linear FEM inflate as it turns while
corotational FEM keeps its volume. The window only reads the engine's state
and talks to it through its public calls: `apply_impulse`, `set_method`,
`set_material`, `settings`, `reset`.

One frame: read input -> step the simulation (real time when it keeps up) ->
draw the bodies, the floor and the panel -> write a stats line.
"""

import json
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import taichi as ti

import fem
import scenes
from app import EXIT_INTERRUPTED, device, orbit, picking
from app.camera import Camera, auto_frame
from app.colors import VertexColoring
from app.display import display_problem
from app import outputs
from app.files import atomic_open, atomic_path, numbered_path, refuse_overwrite
from app.ggui_renderer import _quiet_taichi, _to_ggui_layout
from app.render import background, build_frame
from app.software_renderer import SoftwareRenderer, to_window_layout
from fem.scene import PRECONDITIONERS

PANEL_WIDTH = 0.29              # of the window's width, on the right
LABEL_SIZE = (0.14, 0.04)       # of the window: the title boxes naming the copies of --compare
MAX_STEPS_PER_FRAME = 8
VIDEO_FPS = 30
MARKER_SECONDS = 0.8            # how long a click's hit point and arrow stay drawn
MARKER_COLOR = (1.0, 0.85, 0.1)
DRAG_PIXELS = 6                 # a press and release further apart than this is a drag
HELP = """\
left click      push the body along the view ray
left drag       push along the drag (longer = harder)
right drag      orbit
shift+right or middle drag    pan
ctrl+right drag or up/down    zoom
f   frame the scene again      c   linear <-> corotational
space  pause     n  one step   r   reset the scene
v   start/stop video (mp4)     p   screenshot (png)
l   PCG preconditioner: auto -> two-level -> block Jacobi
scenes: the numbered list in the panel
h   this help                  Esc quit"""


@dataclass
class Press:
    """A left button press waiting for its release: where, and what it hit."""

    pixel: np.ndarray
    hit: picking.Hit | None


def run(args) -> int:
    check_display()
    width, height = parse_size(args.size)
    to_file = args.stats is not None and args.stats != "-"
    if to_file:
        refuse_overwrite(args.stats, args.overwrite)
    device.start(args)
    viewer = Viewer(args, width, height)
    try:
        if to_file:
            with outputs.open_stream(args.stats, args.overwrite) as stats_file:
                viewer.loop(stats_file)
        else:
            viewer.loop(sys.stdout if args.stats == "-" else None)
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


class Viewer:
    def __init__(self, args, width, height):
        self.args, self.width, self.height = args, width, height
        names = list(scenes.builtin_scenes())
        self.scene_refs = names if args.scene in names else [args.scene] + names
        try:
            self.window = ti.ui.Window("softfem", (width, height), vsync=False)
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
        # process ends (gigabytes in an hour). Only the click marker goes through it.
        self.rasteriser = SoftwareRenderer(width, height, smooth=True)
        self.picture = ti.Vector.field(3, ti.f32, (width, height))
        self.marker_point = ti.Vector.field(3, ti.f32, 1)
        self.marker_arrow = ti.Vector.field(3, ti.f32, 16)
        self.sim = None
        self.paused = self.show_help = False
        self.coloring = None
        self.events, self.frame = [], 0
        self.fps, self.frame_seconds, self.render_ms, self.steps_last_frame = 0.0, 0.0, 0.0, 0
        self.press, self.marker, self.marker_until = None, None, 0.0
        self.drag_origin = None
        self.screenshot_due = False
        self.video, self.video_path, self.video_start, self.video_frames = None, None, 0.0, 0
        self.message = ""
        self.load(args.scene)

    # ------------------------------------------------------------ scenes

    def load(self, ref):
        """Build the simulation of a scene; its first frame shows it at rest, then `warm_up`
        compiles every kernel its steps need (a scene of the same kind: none)."""
        self.show_loading(ref)
        args = self.args
        scene = scenes.load_scene(ref, overrides=args.set if Path(str(ref)).suffix != ".txt" else None)
        if args.compare:
            # A gap as wide as the scene, so that a linear copy growing as it turns stays clear of its twin.
            width = np.ptp(np.concatenate([b.mesh.vertices for b in scene.bodies])[:, 0])
            scene = scene.side_by_side(gap=max(0.5, float(width)))
        self.sim = None       # the old scene's fields go back to the pool: a scene of the same kind compiles nothing
        sim = fem.Simulation(scene, method=None if args.compare else args.method, solver=args.solver,
                             dt=args.dt, tolerance=args.tol, max_iterations=args.max_iters, step=args.step)
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
        self.stats = sim.stats()
        self.events.append({"type": "scene", "scene": str(ref), "name": scene.name,
                            "methods": self.methods()})

    def show_loading(self, ref):
        """One frame saying what is loading, since building a scene takes a second or two."""
        with self.gui.sub_window("softfem", 1 - PANEL_WIDTH, 0.0, PANEL_WIDTH, 0.2) as g:
            g.text(f"loading {ref} ...")
            g.text("(compiling kernels the first time)")
        self.canvas.set_image(self.backdrop)
        self.window.show()

    def reset_view(self):
        """Frame the bodies, looking along the scene's own camera direction when it has one,
        and slide them left so the panel does not cover them."""
        self.camera = initial_camera(self.x, self.sim.scene.camera, self.width, self.height,
                                     compare=self.args.compare)

    def methods(self):
        return [b.method for b in self.sim.model.bodies]

    # ------------------------------------------------------------ main loop

    def loop(self, stats_file):
        last = time.perf_counter()
        while self.window.running:
            now = time.perf_counter()
            frame_seconds, last = now - last, now
            # fps from a running mean of the frame time, which a single slow frame barely moves
            self.frame_seconds = 0.9 * self.frame_seconds + 0.1 * frame_seconds if self.frame else frame_seconds
            self.fps = 1.0 / max(self.frame_seconds, 1e-6)
            self.handle_keys()
            self.handle_mouse()
            if not self.window.running:
                break
            if not self.paused and not self.warm_up_due:
                self.advance(frame_seconds)
            self.stats = self.sim.stats()
            self.draw()
            if stats_file:
                row = dict(self.stats, frame=self.frame, events=self.events)
                stats_file.write(json.dumps(row) + "\n")
                stats_file.flush()   # a reader (or a test) can follow the frames as they come
            self.events = []
            self.frame += 1
            if self.warm_up_due:         # the scene is on screen: now compile what its steps need
                warm_up(self.sim)
                self.warm_up_due, last = False, time.perf_counter()
        self.stop_video()

    def advance(self, frame_seconds):
        """Real time when the simulation keeps up (as many steps as the frame took), else one step."""
        dt = self.sim.settings.dt
        step_seconds = self.sim.last.get("wall_ms", 0.0) / 1e3
        steps = 1
        if step_seconds < dt:
            steps = int(np.clip(round(frame_seconds / dt), 1, MAX_STEPS_PER_FRAME))
        for _ in range(steps):
            self.sim.step()
        self.steps_last_frame = steps

    # ------------------------------------------------------------ input

    def handle_keys(self):
        for event in self.window.get_events(ti.ui.PRESS):
            key = event.key
            if key == ti.ui.ESCAPE:
                self.window.running = False
            elif key == " ":
                self.paused = not self.paused
            elif key == "n":
                self.paused = True
                self.sim.step()
            elif key == "r":
                self.reset()
            elif key == "c":
                self.toggle_corotation()
            elif key == "l":
                self.next_preconditioner()
            elif key == "f":
                self.reset_view()
            elif key == "h":
                self.show_help = not self.show_help
            elif key == "p":
                self.screenshot_due = True
            elif key == "v":
                self.toggle_video()
            elif key == ti.ui.UP:
                self.camera = orbit.zoom(self.camera, 0.9)
            elif key == ti.ui.DOWN:
                self.camera = orbit.zoom(self.camera, 1 / 0.9)
            elif key == ti.ui.LMB and self.in_view():
                pixel = self.cursor()
                self.press = Press(pixel, self.pick(pixel))
            elif key in (ti.ui.RMB, ti.ui.MMB):
                self.drag_origin = self.cursor()
        for event in self.window.get_events(ti.ui.RELEASE):
            if event.key == ti.ui.LMB and self.press is not None:
                self.release(self.cursor())
        # After a slow frame (a scene's warm-up) a click's release can come before its press:
        # a press whose button is already up is a whole click.
        if self.press is not None and not self.window.is_pressed(ti.ui.LMB):
            self.release(self.cursor())

    def handle_mouse(self):
        """Right drag orbits; middle drag or shift + right drag pans."""
        right = self.window.is_pressed(ti.ui.RMB)
        middle = self.window.is_pressed(ti.ui.MMB)
        if not (right or middle) or self.drag_origin is None:
            self.drag_origin = None
            return
        pixel = self.cursor()
        dx, dy = pixel - self.drag_origin
        self.drag_origin = pixel
        if middle or self.window.is_pressed(ti.ui.SHIFT):
            self.camera = orbit.pan(self.camera, dx, dy, self.height)
        elif self.window.is_pressed(ti.ui.CTRL):
            self.camera = orbit.zoom(self.camera, float(np.exp(dy / 200)))
        else:
            self.camera = orbit.orbit(self.camera, dx, dy)

    def cursor(self):
        """The mouse position in pixels, (x right, y down) from the top-left corner."""
        x, y = self.window.get_cursor_pos()
        return np.array([x * self.width, (1.0 - y) * self.height])

    def in_view(self):
        """True when the cursor is over the 3D view, not over the panel or the help."""
        x, _ = self.window.get_cursor_pos()
        return x < 1 - PANEL_WIDTH and not self.show_help

    def pick(self, pixel):
        origin, direction = self.camera.ray(pixel[0], pixel[1], self.width, self.height)
        return picking.pick(origin, direction, self.x, self.sim.model.surface)

    def release(self, pixel):
        """A click pushes along the view ray; a drag pushes along the drag, harder the longer it is."""
        press, self.press = self.press, None
        if press.hit is None:
            return
        drag = pixel - press.pixel
        if np.linalg.norm(drag) <= DRAG_PIXELS:
            direction = press.hit.point - self.camera.eye
            strength = self.strength
        else:
            right, true_up, _ = self.camera.basis()
            direction = drag[0] * right - drag[1] * true_up
            strength = self.strength * min(np.linalg.norm(drag) / (0.2 * self.height), 4.0)
        delta_v = strength * direction / np.linalg.norm(direction)
        self.push(press.hit, delta_v)

    def push(self, hit, delta_v):
        """Push the hit body around the hit point; in compare mode its twin gets the same push."""
        model = self.sim.model
        body = int(model.vertex_body_np[hit.vertex])
        span = model.bodies[body].vertices
        ids, dv = picking.push(self.x, np.arange(span.start, span.stop), hit.point, self.radius, delta_v)
        event = {"type": "click", "body": body, "hit_vertex": hit.vertex,
                 "hit_point": hit.point.tolist(), "delta_v": np.asarray(delta_v).tolist(),
                 "vertices": len(ids)}
        if self.twins:
            twin = (body + self.twins) % (2 * self.twins)
            twin_ids = picking.mirrored(ids, self.body_starts, body, twin)
            ids, dv = np.concatenate([ids, twin_ids]), np.concatenate([dv, dv])
            event["twin_body"] = twin
        self.sim.apply_impulse(ids, dv)
        self.events.append(event)
        self.marker = (hit.point, np.asarray(delta_v), "tip")
        self.marker_until = time.perf_counter() + MARKER_SECONDS

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
        """Colour by "body", "volume" or "strain", with the exporter's scales (app.colors)."""
        self.coloring = VertexColoring(self.sim, mode, copies=2 if self.twins else 1)

    def draw(self):
        start = time.perf_counter()
        self.x = self.sim.positions()
        frame = build_frame(self.x, self.sim.model.surface, self.coloring.colors(self.sim), self.camera,
                            ground_y=self.ground_y(), smooth=True)
        self.rasteriser.draw(frame, self.camera)
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
            self.draw_copy_labels()
            self.draw_panel()
            if self.show_help:
                self.draw_help()
            if self.video is not None or self.screenshot_due:
                self.capture()
            self.window.show()
        self.render_ms = 1e3 * (time.perf_counter() - start)

    def ground_y(self):
        """The ground's height, m, or None without a ground: then no floor is drawn."""
        return self.sim.scene.effects.ground

    def draw_copy_labels(self):
        """In compare mode, "linear" and "corotational" at the top of the view, over where the
        copies start. (GGUI places a sub-window once and then leaves it where it is, so the
        labels cannot follow the copies; at the top, a growing copy does not cover them.)"""
        if not self.twins:
            return
        for label, x in zip(copy_methods(self.methods(), self.twins), (x for _, x in self.labels)):
            # ImGui shows the title up to "##"; what follows keeps the two windows apart.
            with self.gui.sub_window(f"{label}##{x:.3f}", x - LABEL_SIZE[0] / 2, 0.01, *LABEL_SIZE) as g:
                g.text("")

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

    # ------------------------------------------------------------ panel

    def draw_panel(self):
        with self.gui.sub_window("softfem", 1 - PANEL_WIDTH, 0.0, PANEL_WIDTH, 1.0) as g:
            g.text(f"{self.sim.scene.name}")
            g.text(f"{self.sim.model.n_tets} tets, {self.sim.model.n_vertices} vertices   [h] help")
            if self.message:
                g.text(self.message)
            if g.button("run" if self.paused else "pause"):
                self.paused = not self.paused
            if g.button("step"):
                self.paused = True
                self.sim.step()
            if g.button("reset"):
                self.reset()
            for section in (self.draw_stats, self.draw_methods, self.draw_impulse, self.draw_colors,
                            self.draw_solver, self.draw_material, self.draw_scenes):
                g.text("")
                section(g)

    def draw_stats(self, g):
        s = self.stats
        g.text("Numbers")
        g.text(f"{self.fps:5.1f} fps, {self.steps_last_frame} step(s)/frame, t = {s['t']:.2f} s"
               + ("  PAUSED" if self.paused else ""))
        g.text(f"ms/step: rotations {s.get('rotation_ms', 0):.1f}, solve {s.get('solve_ms', 0):.1f}")
        g.text(f"ms/frame rendering: {self.render_ms:.1f}")
        residual = s.get("residual")
        preconditioner = f" ({s['preconditioner']})" if s.get("preconditioner") else ""
        g.text(f"{s.get('solver', self.sim.settings.method)}{preconditioner}: {s.get('solver_iters', 0)} iterations, "
               f"residual {residual if residual is not None else float('nan'):.1e}"
               + ("" if s.get("converged", True) else "  NOT CONVERGED"))
        for body, ratio in zip(self.sim.model.bodies, s["volume_ratio"]):
            g.text(f"volume {100 * ratio:6.1f} %  {shown_name(body, self.twins)}")
        g.text(f"kinetic {s['kinetic_energy']:.3g} J, elastic {s['elastic_energy']:.3g} J")
        g.text(f"inverted tets: {s['inverted_tets']}")

    def draw_methods(self, g):
        g.text("Method  (c toggles all)")
        methods = self.methods()
        all_corotational = all(m == "corotational" for m in methods)
        if g.checkbox("corotational (all bodies)", all_corotational) != all_corotational:
            self.toggle_corotation()
            return
        wanted = ["corotational" if g.checkbox(f"{i}: {shown_name(b, self.twins)}", m == "corotational") else "linear"
                  for i, (b, m) in enumerate(zip(self.sim.model.bodies, methods))]
        if wanted != methods:
            self.set_methods(wanted)

    def draw_impulse(self, g):
        g.text("Click impulse")
        self.strength = g.slider_float("strength [m/s]", self.strength, 0.0, 5.0 * self.size)
        self.radius = g.slider_float("radius [m]", self.radius, 0.01 * self.size, 0.5 * self.size)

    def draw_colors(self, g):
        g.text("Colour")
        for mode in ("body", "volume", "strain"):
            if g.checkbox(f"{mode}", self.coloring.mode == mode) and self.coloring.mode != mode:
                self.set_color_mode(mode)
        if self.coloring.mode == "volume":
            g.text(f"volume ratio J: blue {self.coloring.vmin}, grey 1, red {self.coloring.vmax}")
        elif self.coloring.mode == "strain":
            g.text(f"strain energy 0 .. {self.coloring.vmax:.3g} J/m^3 (grows, never shrinks)")

    def draw_solver(self, g):
        """Solver settings; the engine reads them at every step."""
        g.text("Solver")
        settings, effects = self.sim.settings, self.sim.scene.effects
        if g.button(f"solver: {settings.method} (switch)"):
            settings.method = "jacobi" if settings.method == "pcg" else "pcg"
        if settings.method == "pcg":
            chosen = self.sim.solver.preconditioner
            name = settings.preconditioner + (f" ({chosen})" if settings.preconditioner == "auto" else "")
            if g.button(f"preconditioner: {name} (l)"):
                self.next_preconditioner()
        exponent = g.slider_int("tolerance 1e-k", round(-np.log10(settings.tolerance)), 1, 10)
        settings.tolerance = 10.0 ** -exponent
        settings.max_iterations = g.slider_int("max iterations", settings.max_iterations, 1, 1000)
        settings.dt = max(g.slider_float("dt [s]", settings.dt, 0.001, 0.05), 1e-4)
        effects.alpha = g.slider_float("damping alpha", effects.alpha, 0.0, 2.0)
        effects.beta = g.slider_float("damping beta", effects.beta, 0.0, 0.5)

    def draw_scenes(self, g):
        g.text("Scenes")
        for number, ref in enumerate(self.scene_refs[:9], start=1):
            if g.button(f"{number} {Path(str(ref)).stem}"):
                self.switch_scene(ref)

    def draw_material(self, g):
        """E and nu of one body, applied when the slider is let go (changing them rebuilds
        the preconditioner, and each drag position would otherwise be a new material)."""
        bodies = self.sim.model.bodies
        g.text("Material")
        if len(bodies) > 1:
            self.material_body = g.slider_int("body", self.material_body, 0, len(bodies) - 1)
        material = bodies[self.material_body].material
        body, E, nu = self.material_edit or (self.material_body, material.E, material.nu)
        if body != self.material_body:
            body, E, nu = self.material_body, material.E, material.nu
        log_E = g.slider_float("log10 E [Pa]", float(np.log10(E)), 1.0, 8.0)
        nu = g.slider_float("nu", nu, 0.0, 0.49)
        E = 10.0 ** log_E
        g.text(f"{bodies[body].name}: E = {E:.4g} Pa, nu = {nu:.3f}")
        changed = not (np.isclose(E, material.E) and np.isclose(nu, material.nu))
        self.material_edit = (body, E, nu) if changed else None
        if changed and not self.window.is_pressed(ti.ui.LMB):
            self.sim.set_material(body, E, nu)
            self.events.append({"type": "material", "body": body, "E": E, "nu": nu})
            self.material_edit = None

    def draw_help(self):
        lines = HELP.splitlines()
        with self.gui.sub_window("help (h to close)", 0.05, 0.1, 0.6, 0.045 * len(lines) + 0.06) as g:
            for line in lines:
                g.text(line)

    def switch_scene(self, ref):
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
    camera = auto_frame(lo, hi, direction=direction, aspect=width * (1 - PANEL_WIDTH) / height)
    # Sliding the camera right moves the scene left, to the middle of the uncovered part.
    return orbit.pan(camera, -PANEL_WIDTH * width / 2, 0.0, height)


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


def shown_name(body, twins):
    """A body's name in the panel; in compare mode with its method now, not the one it began with."""
    if not twins:
        return body.name
    base = re.sub(r" \((linear|corotational)\)$", "", body.name)
    return f"{base} ({body.method})"
