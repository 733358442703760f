"""What every renderer shares: the frame's geometry, lights, floor, shadow and background.

A renderer turns one frame (surface of the bodies, per-vertex colours, camera)
into an image. Both back ends (`ggui`, `software`) draw the very same triangles
with the same lighting formula, so their pictures can be compared pixel by pixel:

    colour * (AMBIENT + sum over lights of intensity * max(0, n . l))

with l the unit vector from the surface point to each point light (as in GGUI's
shader). The lights follow the camera: a key light above and to the left of the
viewer, far away so it acts like the sun, and a weaker headlight at the eye.

A floor is drawn only where the scene has a ground: a body floating in space
drawn over a floor would seem to stand on it and then fly away. On the floor,
each body casts a contact shadow (its outline seen from straight above), so
how high it is can be judged from the gap between the two.
"""

from dataclasses import dataclass

import numpy as np
import taichi as ti

from app.render.camera import Camera

AMBIENT = 0.3
KEY_LIGHT = 0.5
HEADLIGHT = 0.35
BACKGROUND_TOP = np.array([0.60, 0.66, 0.75])
BACKGROUND_BOTTOM = np.array([0.90, 0.91, 0.93])
FLOOR_LIGHT = np.array([0.88, 0.88, 0.87])
FLOOR_DARK = np.array([0.79, 0.80, 0.81])
FLOOR_TILES = 24  # per side
SHADOW_DARKNESS = 0.6  # the shadow's colour is the floor's times this


@dataclass
class Frame:
    """Triangles ready to draw: the bodies' surface followed by the floor.

    positions (m, 3) f32 metres, normals (m, 3) f32 unit, colors (m, 3) f32 in
    [0, 1], triangles (k, 3) i32, counter-clockwise seen from outside;
    light_positions (2, 3) f32 and light_intensities (2,) f32 for the key light
    and the headlight.
    """

    positions: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    triangles: np.ndarray
    light_positions: np.ndarray
    light_intensities: np.ndarray


class Renderer:
    """Draws a frame into an (height, width, 3) uint8 RGB image."""

    name = "base"

    def __init__(self, width: int, height: int, smooth: bool = True):
        """width, height in pixels; smooth: interpolate normals across triangles
        (True) or shade each triangle flat, showing the mesh's facets (False)."""
        self.width, self.height, self.smooth = width, height, smooth

    def render(self, vertices, faces, colors, camera: Camera, ground_y=None) -> np.ndarray:
        """Image of a surface mesh, shape (height, width, 3), uint8.

        vertices (n, 3) metres; faces (k, 3) int, counter-clockwise seen from
        outside; colors (n, 3) in [0, 1]; ground_y: height of the ground in
        metres, or None for no ground (no floor, no shadow).
        """
        raise NotImplementedError


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals (n, 3): the area-weighted mean of the adjacent faces' normals."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    face_normals = np.cross(b - a, c - a)  # length is twice the area: the weight
    normals = np.zeros_like(vertices)
    for axis in range(3):
        weights = np.repeat(face_normals[:, axis], 3)
        normals[:, axis] = np.bincount(faces.ravel(), weights, minlength=len(vertices))
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)


def surface(vertices, faces, colors, smooth: bool):
    """Positions, normals, colours and triangles of the bodies' surface.

    Flat shading gives every triangle its own three vertices, so that one
    normal per vertex can be one normal per face.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int32)
    colors = np.asarray(colors, dtype=np.float64)
    if smooth:
        return vertices, vertex_normals(vertices, faces), colors, faces
    corners = vertices[faces].reshape(-1, 3)
    unshared = np.arange(len(corners), dtype=np.int32).reshape(-1, 3)
    return corners, vertex_normals(corners, unshared), colors[faces].reshape(-1, 3), unshared


def nice_step(length: float) -> float:
    """The number 1, 2 or 5 times a power of ten closest below `length`."""
    power = 10.0 ** np.floor(np.log10(length))
    return max(s * power for s in (1.0, 2.0, 5.0) if s * power <= length)


def floor(camera: Camera, ground_y: float):
    """A checkered floor at height ground_y (metres) under the camera's target.

    Tiles have a round size (1, 2 or 5 times a power of ten metres) and sit on
    multiples of it, so the floor gives a sense of scale and stays put while
    bodies move. The checker fades out with distance so the floor's edge is soft.
    Returns positions (4T, 3), normals (4T, 3), colors (4T, 3), triangles (2T, 3).
    """
    distance = np.linalg.norm(camera.eye - camera.target)
    step = nice_step(distance / 8)
    centre = np.round(camera.target[[0, 2]] / step) * step
    ticks = (np.arange(FLOOR_TILES) - FLOOR_TILES // 2) * step
    i, j = np.meshgrid(np.arange(FLOOR_TILES), np.arange(FLOOR_TILES), indexing="ij")
    x0 = centre[0] + ticks[i.ravel()]
    z0 = centre[1] + ticks[j.ravel()]
    corners_x = np.stack([x0, x0, x0 + step, x0 + step], axis=1)
    corners_z = np.stack([z0, z0 + step, z0 + step, z0], axis=1)
    positions = np.stack([corners_x, np.full_like(corners_x, ground_y), corners_z], axis=2)
    positions = positions.reshape(-1, 3)

    dark = ((i + j) % 2 == 1).ravel()
    tile_color = np.where(dark[:, None], FLOOR_DARK, FLOOR_LIGHT)
    tile_color = np.repeat(tile_color, 4, axis=0)
    radius = np.linalg.norm(positions[:, [0, 2]] - centre, axis=1) / (FLOOR_TILES // 2 * step)
    fade = np.clip(1.0 - radius, 0.0, 1.0)[:, None] ** 0.5
    colors = fade * tile_color + (1 - fade) * (FLOOR_LIGHT + FLOOR_DARK) / 2

    first = 4 * np.arange(FLOOR_TILES * FLOOR_TILES, dtype=np.int32)[:, None]
    # Counter-clockwise seen from above, so the floor's front faces the sky.
    triangles = np.concatenate([first + [0, 1, 2], first + [0, 2, 3]]).astype(np.int32)
    normals = np.tile([0.0, 1.0, 0.0], (len(positions), 1))
    return positions, normals, colors, triangles


def lights(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Point lights (positions (2, 3), intensities (2,)): key light, headlight."""
    right, true_up, forward = camera.basis()
    distance = np.linalg.norm(camera.eye - camera.target)
    key_direction = -0.5 * right + 1.5 * true_up - 0.5 * forward
    key_direction /= np.linalg.norm(key_direction)
    # A thousand scene sizes away the key light's direction barely changes across the scene.
    key_position = camera.target + 1000.0 * distance * key_direction
    return np.array([key_position, camera.eye]), np.array([KEY_LIGHT, HEADLIGHT])


def shadow(vertices: np.ndarray, faces: np.ndarray, camera: Camera, ground_y: float):
    """The bodies' contact shadow on the ground: their triangles flattened onto it from above.

    A hair above the floor, so it wins the depth test against it, and facing up.
    Returns positions (3k, 3), normals (3k, 3), colors (3k, 3), triangles (k, 3).
    """
    lift = 1e-3 * np.linalg.norm(camera.eye - camera.target)
    corners = np.asarray(vertices, dtype=np.float64)[faces].reshape(-1, 3)
    corners[:, 1] = ground_y + lift
    triangles = np.arange(len(corners), dtype=np.int32).reshape(-1, 3)
    colors = np.tile(SHADOW_DARKNESS * (FLOOR_LIGHT + FLOOR_DARK) / 2, (len(corners), 1))
    return corners, np.tile([0.0, 1.0, 0.0], (len(corners), 1)), colors, triangles


def build_frame(vertices, faces, colors, camera: Camera, ground_y, smooth: bool) -> Frame:
    """The bodies' surface, and where there is a ground (ground_y, metres, not None) the
    floor and the bodies' shadow on it, as one list of triangles to draw."""
    parts = [surface(vertices, faces, colors, smooth)]
    if ground_y is not None:
        parts += [floor(camera, ground_y), shadow(vertices, np.asarray(faces), camera, ground_y)]
    offsets = np.cumsum([0] + [len(part[0]) for part in parts[:-1]])
    light_positions, light_intensities = lights(camera)
    f32 = np.float32
    return Frame(
        positions=np.concatenate([part[0] for part in parts]).astype(f32),
        normals=np.concatenate([part[1] for part in parts]).astype(f32),
        colors=np.concatenate([part[2] for part in parts]).astype(f32),
        triangles=np.concatenate([part[3] + offset for part, offset in zip(parts, offsets)]).astype(np.int32),
        light_positions=light_positions.astype(f32),
        light_intensities=light_intensities.astype(f32),
    )


class FrameBuffers:
    """Taichi fields holding the latest Frame's vertices and triangles.

    Fields are allocated with room to spare (a power of two) and reallocated
    only when a frame does not fit, so a simulation whose surface keeps its
    size uploads into the same fields, and kernels compile once.
    Entries past vertex_count / triangle_count are padding.
    """

    def __init__(self):
        self.vertex_count = self.triangle_count = 0
        self.positions = self.normals = self.colors = self.triangles = None

    def upload(self, frame: Frame):
        n, k = len(frame.positions), len(frame.triangles)
        if self.positions is None or n > self.positions.shape[0]:
            capacity = _next_power_of_two(n)
            self.positions, self.normals, self.colors = (
                ti.Vector.field(3, ti.f32, capacity) for _ in range(3))
        if self.triangles is None or k > self.triangles.shape[0]:
            self.triangles = ti.Vector.field(3, ti.i32, _next_power_of_two(k))
        self.positions.from_numpy(_padded(frame.positions, self.positions.shape[0]))
        self.normals.from_numpy(_padded(frame.normals, self.normals.shape[0]))
        self.colors.from_numpy(_padded(frame.colors, self.colors.shape[0]))
        self.triangles.from_numpy(_padded(frame.triangles, self.triangles.shape[0]))
        self.vertex_count, self.triangle_count = n, k


def _next_power_of_two(n: int) -> int:
    return 1 << max(n - 1, 1).bit_length()


def _padded(rows: np.ndarray, length: int) -> np.ndarray:
    out = np.zeros((length,) + rows.shape[1:], dtype=rows.dtype)
    out[: len(rows)] = rows
    return out


def background(width: int, height: int) -> np.ndarray:
    """Vertical gradient behind the scene, shape (height, width, 3), floats in [0, 1]."""
    t = np.linspace(0.0, 1.0, height)[:, None, None]  # 0 at the top row
    column = (1 - t) * BACKGROUND_TOP + t * BACKGROUND_BOTTOM
    return np.broadcast_to(column, (height, width, 3)).astype(np.float32)
