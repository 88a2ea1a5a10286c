"""Blender camera <-> COLMAP pinhole conventions.

COLMAP: x right, y down, z forward; world-to-camera x_cam = R x_world + t; pixel origin at
the image's top-left corner with pixel centres at +0.5. Blender cameras look down their
local -Z with +Y up, so camera-to-world in COLMAP axes is matrix_world @ diag(1, -1, -1, 1).
The intrinsics formulas reproduce Cycles' own projection exactly for every sensor fit,
pixel aspect and lens shift (see /work/shared/BLENDER_NOTES.md).
"""

from __future__ import annotations

import numpy as np

# Flips Blender's camera axes (x right, y up, -z forward) to COLMAP's (x right, y down, z forward).
BLENDER_TO_COLMAP_AXES = np.diag([1.0, -1.0, -1.0, 1.0])


def render_size(render) -> tuple[int, int]:
    """Output width and height in pixels, honouring the resolution percentage."""
    scale = render.resolution_percentage / 100.0
    return int(render.resolution_x * scale), int(render.resolution_y * scale)


def intrinsics_from_blender(camera_data, render) -> np.ndarray:
    """3x3 pinhole K of a perspective Blender camera rendered with `render` settings."""
    width, height = render_size(render)
    aspect_x, aspect_y = render.pixel_aspect_x, render.pixel_aspect_y
    fit = camera_data.sensor_fit
    if fit == "AUTO":
        sensor = camera_data.sensor_width
        fit = "HORIZONTAL" if width * aspect_x >= height * aspect_y else "VERTICAL"
    else:
        sensor = camera_data.sensor_width if fit == "HORIZONTAL" else camera_data.sensor_height
    view_factor = width if fit == "HORIZONTAL" else height * aspect_y / aspect_x
    fx = camera_data.lens / sensor * view_factor
    fy = fx * aspect_x / aspect_y
    cx = width / 2.0 - camera_data.shift_x * view_factor
    cy = height / 2.0 + camera_data.shift_y * view_factor * aspect_x / aspect_y
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def world_to_camera(matrix_world) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP (R, t) from a Blender camera's matrix_world (which must have unit scale).

    Blender stores matrix_world in float32, so its rotation part is orthonormal only to
    ~1e-7. R is snapped to the nearest true rotation (a ~1e-7 rad change, far below a pixel)
    so that quaternion round trips, e.g. through a COLMAP model, reproduce it exactly; the
    camera centre is kept as Blender has it.
    """
    camera_to_world = np.array(matrix_world, dtype=np.float64) @ BLENDER_TO_COLMAP_AXES
    rotation = nearest_rotation(camera_to_world[:3, :3].T)
    translation = -rotation @ camera_to_world[:3, 3]
    return rotation, translation


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation closest to `matrix` in the Frobenius norm (SVD projection)."""
    u, _, vt = np.linalg.svd(matrix)
    correction = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return u @ correction @ vt


def project(K: np.ndarray, R: np.ndarray, t: np.ndarray, points_world: np.ndarray):
    """Pixel coordinates (N, 2) and camera-space depths (N,) of world points (N, 3)."""
    points_camera = np.asarray(points_world, dtype=np.float64) @ R.T + t
    depth = points_camera[:, 2]
    pixels = (points_camera @ K.T)[:, :2] / depth[:, None]
    return pixels, depth


def backproject(K: np.ndarray, R: np.ndarray, t: np.ndarray, pixels: np.ndarray,
                depth: np.ndarray) -> np.ndarray:
    """World points (N, 3) seen at `pixels` (N, 2) with optical-axis depth `depth` (N,)."""
    homogeneous = np.column_stack([pixels, np.ones(len(pixels))])
    points_camera = (homogeneous @ np.linalg.inv(K).T) * depth[:, None]
    return (points_camera - t) @ R
