"""The window's side panel and help: a part of `Viewer` (app/window/viewer.py), whose attributes
it reads and sets through the panel's buttons, checkboxes and sliders."""

import re
import textwrap
import time
from pathlib import Path

import numpy as np
import taichi as ti

# GGUI's font (ImGui's ProggyClean, 13 px) gives every character 7 pixels and every line 17.
CHAR_WIDTH, LINE_HEIGHT = 7, 17
# The panel's widest line. A slider takes 65 % of the panel and its label (up to 14 characters,
# "strength [m/s]") the rest, which needs a panel this wide; longer text wraps.
PANEL_CHARS = 50
PANEL_MARGIN = 30               # px beside the text: the padding (8 each side) and the scroll bar (14)
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
t   contact points (magenta dots where bodies touch)
scenes: the numbered list in the panel
h   this help                  Esc quit"""


class Panel:
    """The panel and the help window of the Viewer (a mixin: the Viewer holds the state)."""

    def draw_panel(self):
        width = panel_width(self.width)
        with self.gui.sub_window("softfem", 1 - width, 0.0, width, 1.0) as g:
            self.text(g, self.sim.scene.name)
            self.text(g, f"{self.sim.model.n_tets} tets, {self.sim.model.n_vertices} vertices   [h] help")
            if self.message:
                self.text(g, self.message)
            if g.button("run" if self.paused else "pause"):
                self.paused = not self.paused
            if g.button("step"):
                self.paused = True
                self.sim.step()
            if g.button("reset"):
                self.reset()
            for section in (self.draw_stats, self.draw_methods, self.draw_impulse, self.draw_colors,
                            self.draw_contact, self.draw_solver, self.draw_material, self.draw_scenes):
                g.text("")
                section(g)

    def draw_compiling(self, g):
        """The panel while kernels compile: what, how far, and the input waiting for them."""
        self.text(g, self.sim.scene.name if self.sim is not None else f"loading {self.compiling.name}")
        self.text(g, self.compiling.status(time.monotonic()))
        if self.stats is not None:       # the scene is built: where it stands (at rest)
            self.text(g, numbers(self.stats, None, 0, None, self.paused)[0])
        if self.waiting:
            keys = [e.key for e in self.waiting if e.pressed]
            self.text(g, "waiting for them: " + " ".join("click" if key == ti.ui.LMB else key for key in keys))

    def text(self, g, text):
        """text in the panel, wrapped at its width (a long path breaks anywhere)."""
        for line in textwrap.wrap(text, panel_chars(self.width)) or [""]:
            g.text(line)

    def fit(self, label, room=4):
        """label of a button or checkbox, shortened to fit the panel with `room` characters
        beside it (the box, a button's frame)."""
        return shortened(label, panel_chars(self.width) - room)

    def draw_stats(self, g):
        s = self.stats
        g.text("Numbers")
        for line in numbers(s, self.fps, self.steps_last_frame, self.render_ms, self.paused):
            self.text(g, line)
        for body, ratio in zip(self.sim.model.bodies, s["volume_ratio"]):
            self.text(g, f"volume {100 * ratio:6.1f} %  {shown_name(body, self.twins)}")
        self.text(g, f"kinetic {s['kinetic_energy']:.3g} J, elastic {s['elastic_energy']:.3g} J")
        self.text(g, f"inverted tets: {s['inverted_tets']}")

    def draw_methods(self, g):
        g.text("Method  (c toggles all)")
        methods = self.methods()
        all_corotational = all(m == "corotational" for m in methods)
        if g.checkbox("corotational (all bodies)", all_corotational) != all_corotational:
            self.toggle_corotation()
            return
        wanted = ["corotational" if g.checkbox(self.fit(f"{i}: {shown_name(b, self.twins)}"), m == "corotational")
                  else "linear"
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
            self.text(g, f"volume ratio J: blue {self.coloring.vmin}, grey 1, red {self.coloring.vmax}")
        elif self.coloring.mode == "strain":
            self.text(g, f"strain energy 0 .. {self.coloring.vmax:.3g} J/m^3 (grows, never shrinks)")

    def draw_contact(self, g):
        """The contact points' toggle, and how many there are (drawn over the bodies)."""
        g.text("Contact")
        if g.checkbox("contact points (t)", self.show_contacts) != self.show_contacts:
            self.toggle_contact_points()
        if self.sim.scene.effects.contact is None:
            self.text(g, "none: no contact in this scene (--contact)")
        elif self.show_contacts:
            self.text(g, f"{len(self.sim.contact_points)} points where bodies touch (magenta)")

    def draw_solver(self, g):
        """Solver settings; the engine reads them at every step."""
        g.text("Solver")
        settings, effects = self.sim.settings, self.sim.scene.effects
        if g.button(f"solver: {settings.method} (switch)"):
            settings.method = "jacobi" if settings.method == "pcg" else "pcg"
        if settings.method == "pcg":
            chosen = self.sim.solver.preconditioner
            name = settings.preconditioner + (f" ({chosen})" if settings.preconditioner == "auto" else "")
            if g.button(self.fit(f"preconditioner: {name} (l)")):
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
            if g.button(self.fit(f"{number} {Path(str(ref)).stem}")):
                self.scene_due = ref        # loaded at the next frame's start, not inside this one

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
        self.text(g, f"{bodies[body].name}: E = {E:.4g} Pa, nu = {nu:.3f}")
        changed = not (np.isclose(E, material.E) and np.isclose(nu, material.nu))
        self.material_edit = (body, E, nu) if changed else None
        if changed and not self.window.is_pressed(ti.ui.LMB):
            self.sim.set_material(body, E, nu)
            self.events.append({"type": "material", "body": body, "E": E, "nu": nu})
            self.material_edit = None

    def draw_help(self):
        lines = HELP.splitlines()
        # sized to the text: the padding (8 each side) and the title bar (19 px) beside it
        width = (max(map(len, lines)) * CHAR_WIDTH + 16) / self.width
        height = (len(lines) * LINE_HEIGHT + 19 + 16) / self.height
        with self.gui.sub_window("help (h to close)", 0.02, 0.05, min(width, 0.96), min(height, 0.9)) as g:
            for line in lines:
                g.text(line)


def panel_width(window_width) -> float:
    """The panel's width, a fraction of the window's: room for PANEL_CHARS characters, but
    no more than half a small window."""
    return min(PANEL_CHARS * CHAR_WIDTH + PANEL_MARGIN, window_width / 2) / window_width


def panel_chars(window_width) -> int:
    """How many characters a line of the panel holds in a window window_width pixels wide."""
    return int(panel_width(window_width) * window_width - PANEL_MARGIN) // CHAR_WIDTH


def numbers(stats, fps, steps_per_frame, render_ms, paused) -> list[str]:
    """The panel's lines on time, speed and the last solve. A figure not measured yet is not
    shown: the frame rate before two frames are timed, the solve before the first step.
    stats: Simulation.stats(); fps: frames per second or None; render_ms: ms or None."""
    lines = [f"t = {stats['t']:.2f} s, step {stats['step']}" + ("   PAUSED" if paused else ""),
             f"{fps:.1f} fps, {steps_per_frame} step(s)/frame" if fps is not None else "fps: measuring"]
    if render_ms is not None:
        lines.append(f"ms/frame rendering: {render_ms:.1f}")
    if "residual" not in stats:
        return lines + [f"{stats['solver']}: no step yet"]
    preconditioner = f" ({stats['preconditioner']})" if stats.get("preconditioner") else ""
    residual = "not measured" if stats["residual"] is None else f"{stats['residual']:.1e}"
    return lines + [f"ms/step: rotations {stats['rotation_ms']:.1f}, solve {stats['solve_ms']:.1f}",
                    f"{stats['solver']}{preconditioner}: {stats['solver_iters']} iterations",
                    f"residual {residual}" + ("" if stats.get("converged", True) else "  NOT CONVERGED")]


def shortened(text, chars) -> str:
    """text, or its start and "..." when it is longer than chars."""
    return text if len(text) <= chars else text[:max(chars - 3, 1)] + "..."


def shown_name(body, twins):
    """A body's name in the panel; in compare mode with its method now, not the one it began with."""
    if not twins:
        return body.name
    base = re.sub(r" \((linear|corotational)\)$", "", body.name)
    return f"{base} ({body.method})"
