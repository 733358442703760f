"""Moving a Camera with the mouse: orbit about the target, pan, zoom.

Each function returns a new Camera and leaves its argument alone. Mouse moves
are in pixels, x to the right and y down, as windows report them.
"""

from dataclasses import replace

import numpy as np

from app.render.camera import Camera

ORBIT_DEGREES_PER_PIXEL = 0.3
MAX_ELEVATION_DEGREES = 89.0   # stop short of the poles, where "up" is undefined


def orbit(camera: Camera, dx: float, dy: float) -> Camera:
    """Turn the eye about the target: dx pixels spin it about the world's y axis,
    dy pixels raise or lower it (a drag upwards shows the scene from below)."""
    offset = camera.eye - camera.target
    distance = np.linalg.norm(offset)
    azimuth = np.arctan2(offset[0], offset[2]) - np.radians(ORBIT_DEGREES_PER_PIXEL * dx)
    elevation = np.arcsin(np.clip(offset[1] / distance, -1.0, 1.0)) + np.radians(ORBIT_DEGREES_PER_PIXEL * dy)
    limit = np.radians(MAX_ELEVATION_DEGREES)
    elevation = np.clip(elevation, -limit, limit)
    direction = np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation),
                          np.cos(elevation) * np.cos(azimuth)])
    return replace(camera, eye=camera.target + distance * direction, up=np.array([0.0, 1.0, 0.0]))


def pan(camera: Camera, dx: float, dy: float, height: int) -> Camera:
    """Slide eye and target together so the point under the cursor follows it
    (exactly so at the target's depth); height: image height in pixels."""
    right, true_up, _ = camera.basis()
    distance = np.linalg.norm(camera.eye - camera.target)
    metres_per_pixel = 2.0 * distance * np.tan(np.radians(camera.fov_deg) / 2) / height
    shift = metres_per_pixel * (-dx * right + dy * true_up)
    return replace(camera, eye=camera.eye + shift, target=camera.target + shift)


def zoom(camera: Camera, factor: float) -> Camera:
    """Move the eye towards the target (factor < 1) or away from it (factor > 1);
    the clipping planes follow, so depth precision stays the same."""
    return replace(camera, eye=camera.target + factor * (camera.eye - camera.target),
                   near=camera.near * factor, far=camera.far * factor)
