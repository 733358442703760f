"""A rasteriser written as Taichi kernels: pictures without a GPU or Vulkan.

Three passes per frame:
1. project: every vertex to pixel coordinates (x right, y down) and 1/w.
2. rasterise: every triangle scans the pixels of its bounding box and, where it
   covers a pixel centre, offers a key (depth, triangle index) packed in one
   64-bit integer; atomic_max keeps the nearest. Integer keys make the winner
   independent of thread order, so the same input gives the same image, byte
   for byte, and ties between equally near triangles go to the higher index.
3. shade: every pixel looks up its winning triangle and lights it, or shows
   the background.

Triangles that reach behind the near plane are skipped rather than clipped:
a camera placed inside the scene loses the triangles touching it.
"""

import numpy as np
import taichi as ti

from app.render.frame import AMBIENT, FrameBuffers, Renderer, background, build_frame

DEPTH_LEVELS = 2**31 - 1  # depth is stored in the key's upper 32 bits
NO_TRIANGLE = -1
COVERAGE_TOLERANCE = 1e-5  # in barycentric units: shared edges leave no cracks

Mat4 = ti.types.matrix(4, 4, ti.f32)
Vec2 = ti.types.vector(2, ti.f32)
LightPositions = ti.types.matrix(2, 3, ti.f32)  # one light per row


@ti.func
def edge(a, b, p):
    """Twice the signed area of triangle (a, b, p) in pixel coordinates."""
    return (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x)


@ti.func
def barycentrics(a, b, c, p):
    """Weights (3,) of a, b, c at pixel point p; all >= 0 inside the triangle."""
    area = edge(a, b, c)
    return ti.Vector([edge(b, c, p), edge(c, a, p), edge(a, b, p)]) / area


@ti.kernel
def project(positions: ti.template(), screen: ti.template(), count: ti.i32,
            view_proj: Mat4, width: ti.i32, height: ti.i32):
    """screen[i] = (column, row, 1/w, w) of vertex i, with w its distance along
    the view direction (metres) and pixel centres at half-integers."""
    for i in range(count):
        clip = view_proj @ ti.Vector([positions[i].x, positions[i].y, positions[i].z, 1.0], ti.f32)
        inv_w = 1.0 / clip.w  # inf for w = 0, but rasterise skips vertices that close
        column = (clip.x * inv_w + 1.0) * 0.5 * width
        row = (1.0 - clip.y * inv_w) * 0.5 * height
        screen[i] = ti.Vector([column, row, inv_w, clip.w], ti.f32)


@ti.kernel
def rasterise(screen: ti.template(), triangles: ti.template(), count: ti.i32,
              visible: ti.template(), near: ti.f32, far: ti.f32):
    """visible[row, column] = max over covering triangles t of (depth key << 32 | t)."""
    height, width = visible.shape
    for t in range(count):
        a, b, c = screen[triangles[t][0]], screen[triangles[t][1]], screen[triangles[t][2]]
        area = edge(a, b, c)
        # Skip triangles reaching behind the near plane, and degenerate ones (no area, no pixels).
        if ti.min(a.w, b.w, c.w) >= near and ti.abs(area) > 1e-12:
            x0 = ti.max(ti.cast(ti.floor(ti.min(a.x, b.x, c.x)), ti.i32), 0)
            x1 = ti.min(ti.cast(ti.ceil(ti.max(a.x, b.x, c.x)), ti.i32), width - 1)
            y0 = ti.max(ti.cast(ti.floor(ti.min(a.y, b.y, c.y)), ti.i32), 0)
            y1 = ti.min(ti.cast(ti.ceil(ti.max(a.y, b.y, c.y)), ti.i32), height - 1)
            for y, x in ti.ndrange((y0, y1 + 1), (x0, x1 + 1)):
                weights = barycentrics(a.xy, b.xy, c.xy, Vec2(x + 0.5, y + 0.5))
                if weights.min() >= -COVERAGE_TOLERANCE:
                    # 1/w is affine in screen space, so it interpolates exactly.
                    inv_w = weights.dot(ti.Vector([a.z, b.z, c.z]))
                    nearness = (inv_w - 1.0 / far) / (1.0 / near - 1.0 / far)  # 1 near, 0 far
                    depth_key = ti.cast(ti.math.clamp(nearness, 0.0, 1.0) * DEPTH_LEVELS, ti.i64)
                    ti.atomic_max(visible[y, x], (depth_key << 32) | ti.cast(t, ti.i64))


@ti.kernel
def shade(visible: ti.template(), screen: ti.template(), triangles: ti.template(),
          positions: ti.template(), normals: ti.template(), colors: ti.template(),
          backdrop: ti.template(), image: ti.template(),
          light_positions: LightPositions, light_intensities: Vec2):
    """image[row, column] = lit colour of the visible triangle, or the backdrop."""
    for y, x in visible:
        key = visible[y, x]
        rgb = backdrop[y, x]
        if key != NO_TRIANGLE:
            t = ti.cast(key & ti.i64(0xFFFFFFFF), ti.i32)
            i, j, k = triangles[t][0], triangles[t][1], triangles[t][2]
            a, b, c = screen[i], screen[j], screen[k]
            weights = barycentrics(a.xy, b.xy, c.xy, Vec2(x + 0.5, y + 0.5))
            # Perspective-correct weights: attributes are affine in 3D, not on screen.
            weights *= ti.Vector([a.z, b.z, c.z])
            weights /= weights.sum()
            point = weights[0] * positions[i] + weights[1] * positions[j] + weights[2] * positions[k]
            normal = (weights[0] * normals[i] + weights[1] * normals[j] + weights[2] * normals[k]).normalized()
            albedo = weights[0] * colors[i] + weights[1] * colors[j] + weights[2] * colors[k]
            light = ti.cast(AMBIENT, ti.f32)
            for m in ti.static(range(2)):
                light_position = ti.Vector([light_positions[m, 0], light_positions[m, 1], light_positions[m, 2]])
                # normalized() works in the default float type, which may be f64.
                lambert = ti.cast(normal.dot((light_position - point).normalized()), ti.f32)
                if lambert > 0:
                    light += light_intensities[m] * lambert
            rgb = albedo * light
        image[y, x] = ti.cast(ti.math.clamp(rgb, 0.0, 1.0) * 255.0 + 0.5, ti.u8)


class SoftwareRenderer(Renderer):
    """Renders on the CPU (or whatever Taichi runs on); needs no Vulkan."""

    name = "software"

    def __init__(self, width: int, height: int, smooth: bool = True):
        super().__init__(width, height, smooth)
        self.buffers = FrameBuffers()
        self.screen = None
        self.visible = ti.field(ti.i64, (height, width))
        self.image = ti.Vector.field(3, ti.u8, (height, width))
        self.backdrop = ti.Vector.field(3, ti.f32, (height, width))
        self.backdrop.from_numpy(background(width, height))

    def render(self, vertices, faces, colors, camera, ground_y=None) -> np.ndarray:
        self.draw(build_frame(vertices, faces, colors, camera, ground_y, self.smooth), camera)
        return self.image.to_numpy()

    def draw(self, frame, camera):
        """Render a Frame into `image` (height, width) u8, left on the device (the window shows it)."""
        buffers = self.buffers
        buffers.upload(frame)
        if self.screen is None or self.screen.shape != buffers.positions.shape:
            self.screen = ti.Vector.field(4, ti.f32, buffers.positions.shape)
        view_proj = camera.view_proj(self.width / self.height).astype(np.float32)
        project(buffers.positions, self.screen, buffers.vertex_count, view_proj,
                self.width, self.height)
        self.visible.fill(NO_TRIANGLE)
        rasterise(self.screen, buffers.triangles, buffers.triangle_count, self.visible,
                  camera.near, camera.far)
        shade(self.visible, self.screen, buffers.triangles, buffers.positions, buffers.normals,
              buffers.colors, self.backdrop, self.image, frame.light_positions,
              frame.light_intensities)


@ti.kernel
def to_window_layout(image: ti.template(), out: ti.template()):
    """out[column, row from the bottom] = image[row from the top, column] / 255: a GGUI canvas image."""
    height = image.shape[0]
    for y, x in image:
        out[x, height - 1 - y] = ti.cast(image[y, x], ti.f32) / 255.0
