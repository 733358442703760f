"""Renders with Taichi GGUI (Vulkan) into an offscreen window.

The window is never shown, so this also works on a server, given a Vulkan
driver (Mesa's software driver lavapipe will do). GGUI reads images as
(column, row) with row 0 at the bottom; this module hides that.
"""

import contextlib

import numpy as np
import taichi as ti

from app.render.frame import AMBIENT, FrameBuffers, Renderer, background, build_frame

_LOG_LEVELS = ["trace", "debug", "info", "warn", "error", "critical"]


@contextlib.contextmanager
def _quiet_taichi():
    """Silence Taichi's log below errors for a while: GGUI logs every image it
    reads back, and its own kernels warn about precision when default_fp is f64."""
    current = next(level for level in _LOG_LEVELS if ti._logging.is_logging_effective(level))
    if _LOG_LEVELS.index(current) < _LOG_LEVELS.index("error"):
        ti.set_logging_level("error")
    try:
        yield
    finally:
        ti.set_logging_level(current)


def _to_ggui_layout(image: np.ndarray) -> np.ndarray:
    """(H, W, C) image, row 0 at the top -> (W, H, C), row 0 at the bottom."""
    return np.ascontiguousarray(image[::-1].transpose(1, 0, 2))


class GGUIRenderer(Renderer):
    """Renders through Vulkan; raises RuntimeError when no Vulkan driver works."""

    name = "ggui"

    def __init__(self, width: int, height: int, smooth: bool = True):
        super().__init__(width, height, smooth)
        self.window = ti.ui.Window("soft-body renderer", (width, height), show_window=False)
        self.canvas = self.window.get_canvas()
        self.scene = self.window.get_scene()
        self.camera = ti.ui.Camera()
        self.buffers = FrameBuffers()
        self.backdrop = ti.Vector.field(3, ti.f32, (width, height))
        self.backdrop.from_numpy(_to_ggui_layout(background(width, height)))

    def render(self, vertices, faces, colors, camera, ground_y=None) -> np.ndarray:
        frame = build_frame(vertices, faces, colors, camera, ground_y, self.smooth)
        self.buffers.upload(frame)
        self.camera.position(*camera.eye)
        self.camera.lookat(*camera.target)
        self.camera.up(*camera.basis()[1])       # the screen's up: defined for a top-down camera too
        self.camera.fov(camera.fov_deg)
        self.camera.z_near(camera.near)
        self.camera.z_far(camera.far)
        # GGUI reads the indices through a pointer when it draws: keep them alive till then.
        indices = np.ascontiguousarray(frame.triangles.ravel())
        with _quiet_taichi():
            # The backdrop must be set first: set after the mesh, it hides the scene.
            self.canvas.set_image(self.backdrop)
            self.scene.set_camera(self.camera)
            self.scene.ambient_light((AMBIENT,) * 3)
            for position, intensity in zip(frame.light_positions, frame.light_intensities):
                self.scene.point_light(tuple(position), (float(intensity),) * 3)
            self.scene.mesh(self.buffers.positions, indices=indices,
                            normals=self.buffers.normals, per_vertex_color=self.buffers.colors)
            self.canvas.scene(self.scene)
            rgba = self.window.get_image_buffer_as_numpy()
        # GGUI stores 8-bit colours; scaling back by 255 and rounding recovers them exactly.
        return np.round(rgba[:, ::-1, :3].transpose(1, 0, 2) * 255).astype(np.uint8)
