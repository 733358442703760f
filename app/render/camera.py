"""Pinhole camera shared by every renderer.

Conventions (the same as OpenGL and Taichi GGUI): right-handed world, y up, the
camera looks down its own -z axis, clip space is [-1, 1]^3 after division by w.
Image pixels are indexed (row, column) with row 0 at the top.
"""

from dataclasses import dataclass, field

import numpy as np


def _vec3(value) -> np.ndarray:
    return np.asarray(value, dtype=np.float64).reshape(3)


@dataclass
class Camera:
    """Where the camera is and what it sees.

    eye, target, up: world positions / direction, shape (3,), in metres.
    fov_deg: vertical field of view in degrees.
    near, far: distances of the clipping planes from the eye, in metres; geometry
        closer than `near` is not drawn.
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fov_deg: float = 45.0
    near: float = 0.01
    far: float = 100.0

    def __post_init__(self):
        self.eye, self.target, self.up = _vec3(self.eye), _vec3(self.target), _vec3(self.up)

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit vectors (right, true_up, forward) of the camera in world space."""
        forward = self.target - self.eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        if np.linalg.norm(right) < 1e-6:      # looking straight along up (top-down): screen up is -z
            right = np.cross(forward, [0.0, 0.0, -1.0])
        right /= np.linalg.norm(right)
        return right, np.cross(right, forward), forward

    def view(self) -> np.ndarray:
        """World-to-camera matrix, shape (4, 4), acting on column vectors."""
        right, true_up, forward = self.basis()
        view = np.eye(4)
        view[0, :3], view[1, :3], view[2, :3] = right, true_up, -forward
        view[:3, 3] = -view[:3, :3] @ self.eye
        return view

    def projection(self, aspect: float) -> np.ndarray:
        """Camera-to-clip perspective matrix, shape (4, 4); aspect = width / height."""
        f = 1.0 / np.tan(np.radians(self.fov_deg) / 2)
        n, far = self.near, self.far
        return np.array([
            [f / aspect, 0, 0, 0],
            [0, f, 0, 0],
            [0, 0, (far + n) / (n - far), 2 * far * n / (n - far)],
            [0, 0, -1, 0],
        ])

    def view_proj(self, aspect: float) -> np.ndarray:
        """World-to-clip matrix, shape (4, 4): clip = M @ [x, y, z, 1]."""
        return self.projection(aspect) @ self.view()

    def to_pixels(self, points, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Where world points (n, 3), metres, appear in a width x height image: pixel
        coordinates (n, 2), x right and y down from the top-left corner (pixel centres at
        +0.5, as `ray` takes them), and (n,) True for the points in front of the near plane."""
        points = np.reshape(points, (-1, 3))
        clip = np.c_[points, np.ones(len(points))] @ self.view_proj(width / height).T
        ahead = clip[:, 3] >= self.near
        ndc = clip[:, :2] / np.where(ahead, clip[:, 3], 1.0)[:, None]
        return np.c_[(ndc[:, 0] + 1) / 2 * width, (1 - ndc[:, 1]) / 2 * height], ahead

    def ray(self, px: float, py: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """World ray through pixel (px, py), e.g. a mouse click.

        px, py: pixel coordinates, origin at the top-left corner of the image
            (pixel centres at +0.5).
        Returns (origin (3,), unit direction (3,)); origin is the eye.
        """
        right, true_up, forward = self.basis()
        half_h = np.tan(np.radians(self.fov_deg) / 2)
        half_w = half_h * width / height
        x_ndc = 2.0 * px / width - 1.0
        y_ndc = 1.0 - 2.0 * py / height
        direction = forward + x_ndc * half_w * right + y_ndc * half_h * true_up
        return self.eye.copy(), direction / np.linalg.norm(direction)


def auto_frame(bounds_min, bounds_max, direction=(1.0, 0.6, 1.6), fov_deg=45.0,
               aspect=4 / 3) -> Camera:
    """A camera looking at the box [bounds_min, bounds_max] (each (3,), metres).

    The eye sits along `direction` from the box centre, far enough that the
    box's bounding sphere fits in the image with a small margin, for images of
    the given aspect (width / height).
    """
    lo, hi = _vec3(bounds_min), _vec3(bounds_max)
    centre = (lo + hi) / 2
    radius = max(np.linalg.norm(hi - lo) / 2, 1e-6)
    half_v = np.radians(fov_deg) / 2
    half_h = np.arctan(np.tan(half_v) * aspect)
    margin = 1.1
    distance = margin * radius / np.sin(min(half_v, half_h))
    unit = _vec3(direction) / np.linalg.norm(direction)
    # Clip planes scale with the scene so depth precision does not depend on units.
    return Camera(eye=centre + distance * unit, target=centre, fov_deg=fov_deg,
                  near=0.02 * distance, far=20.0 * distance)
