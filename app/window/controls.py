"""The window's mouse and keys: a part of `Viewer` (app/window/viewer.py), whose attributes it
reads and sets. A left click or drag pushes a body (app/window/picking.py); right and middle
drags move the camera (app/window/orbit.py)."""

import time
from dataclasses import dataclass

import numpy as np
import taichi as ti

from app.window import orbit, picking
from app.window.panel import panel_width

MARKER_SECONDS = 0.8            # how long a click's hit point and arrow stay drawn
DRAG_PIXELS = 6                 # a press and release further apart than this is a drag


@dataclass
class Input:
    """A key or mouse button going down (pressed) or up, the cursor's pixel then (x right, y down),
    and when it was seen (time.perf_counter(), s)."""

    key: str
    pressed: bool
    pixel: np.ndarray
    seen: float


@dataclass
class Press:
    """A left button press waiting for its release: where, what it hit, and when it was seen."""

    pixel: np.ndarray
    hit: picking.Hit | None
    seen: float


class Controls:
    """Input handling of the Viewer (a mixin: the Viewer holds the state, `waiting` among it:
    the input read while kernels compiled, kept for the first frame that can step)."""

    def read_input(self):
        """The presses and releases since the last call, with the cursor where it is now. Taichi's
        events carry no order between a press and a release: within one call presses come first."""
        # Reading the events moves Taichi's cursor to where the X server last said it was.
        presses, releases = self.window.get_events(ti.ui.PRESS), self.window.get_events(ti.ui.RELEASE)
        pixel, now = self.cursor(), time.perf_counter()
        return [Input(e.key, True, pixel, now) for e in presses] + [Input(e.key, False, pixel, now) for e in releases]

    def handle_keys(self):
        inputs, self.waiting = self.waiting + self.read_input(), []
        if self.warm_up_due:
            # warm_up starts the scene over, which would undo a push made now: keep it for after.
            self.waiting = inputs
            return
        for event in inputs:
            if event.pressed:
                self.key_pressed(event)
            elif event.key == ti.ui.LMB and self.press is not None:
                self.release(event.pixel)
        # After a slow frame a click's release can come before its press: a press whose button
        # is already up is a whole click.
        if self.press is not None and not self.window.is_pressed(ti.ui.LMB):
            self.release(self.cursor())

    def key_pressed(self, event):
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
        elif key == "t":
            self.toggle_contact_points()
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
        elif key == ti.ui.LMB and self.in_view(event.pixel):
            self.press = Press(event.pixel, self.pick(event.pixel), event.seen)
        elif key in (ti.ui.RMB, ti.ui.MMB):
            self.drag_origin = self.cursor()

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

    def in_view(self, pixel):
        """True when pixel (x right, y down) is in the 3D view, not over the panel or the help."""
        return pixel[0] < (1 - panel_width(self.width)) * self.width and not self.show_help

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
        self.push(press.hit, delta_v, waited_s=time.perf_counter() - press.seen)

    def push(self, hit, delta_v, waited_s=0.0):
        """Push the hit body around the hit point; in compare mode its twin gets the same push.
        waited_s: how long the click waited for the kernels to compile (s), for the click's event."""
        model = self.sim.model
        body = int(model.vertex_body_np[hit.vertex])
        span = model.bodies[body].vertices
        ids, dv = picking.push(self.x, np.arange(span.start, span.stop), hit.point, self.radius, delta_v)
        event = {"type": "click", "body": body, "hit_vertex": hit.vertex,
                 "hit_point": hit.point.tolist(), "delta_v": np.asarray(delta_v).tolist(),
                 "vertices": len(ids), "waited_s": round(waited_s, 2)}
        if self.twins:
            twin = (body + self.twins) % (2 * self.twins)
            twin_ids = picking.mirrored(ids, self.body_starts, body, twin)
            ids, dv = np.concatenate([ids, twin_ids]), np.concatenate([dv, dv])
            event["twin_body"] = twin
        self.sim.apply_impulse(ids, dv)
        self.events.append(event)
        self.marker = (hit.point, np.asarray(delta_v), "tip")
        self.marker_until = time.perf_counter() + MARKER_SECONDS
