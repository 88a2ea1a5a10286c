"""Synthetic-aperture refocus through the light field (Isaksen et al. 2000).

A thin lens of radius `aperture` (scene units) in the camera's image plane, focused at
`focus` (depth along the optical axis): every output pixel averages the rays from points on
the lens aimed at the pixel's point on the focal plane.  Points at the focus depth stay
sharp; others blur by a circle of confusion of radius f_px * aperture * |1/Z - 1/focus|
pixels.  The number of lens samples follows that blur over the scene's depth range, so a
pinhole (or a blur under half a pixel) costs exactly one ray.
"""

from __future__ import annotations

import math

import numpy as np
import torch

MAX_SAMPLES = 96


def aperture_from_f_stop(focal_length: float, f_stop: float) -> float:
    """Thin-lens aperture radius: focal length / (2 N), in the focal length's units."""
    return focal_length / (2.0 * f_stop)


def lens_samples(count: int) -> np.ndarray:
    """(count, 2) points spread evenly over the unit disk (Vogel's sunflower spiral)."""
    if count <= 1:
        return np.zeros((1, 2))
    index = np.arange(count) + 0.5
    radius = np.sqrt(index / count)
    angle = index * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1)


def max_blur_radius_px(focal_px: float, aperture: float, focus: float, z_near: float, z_far: float) -> float:
    """Largest circle of confusion (pixels) of anything between z_near and z_far."""
    return focal_px * aperture * max(abs(1.0 / z_near - 1.0 / focus), abs(1.0 / z_far - 1.0 / focus))


def sample_count(blur_radius_px: float, max_samples: int = MAX_SAMPLES) -> int:
    """About one lens sample per pixel of the largest blur disc, at least 1, at most `max_samples`."""
    if blur_radius_px < 0.5:
        return 1
    return int(min(max_samples, max(4, math.ceil(math.pi * blur_radius_px ** 2))))


def lens_rays(origin: torch.Tensor, directions: torch.Tensor, R: np.ndarray, focus: float, aperture: float,
              lens_point: np.ndarray):
    """Rays (origins (N, 3), unit directions (N, 3)) from one lens point through each pixel's
    focal point.  `origin`, `directions`: the pinhole camera's centre and pixel rays (world);
    `lens_point`: a point of the unit disk; `R`: world-to-camera rotation."""
    R_t = torch.as_tensor(np.asarray(R), device=directions.device, dtype=directions.dtype)
    forward = R_t[2]
    focal_points = origin + directions * (focus / (directions @ forward))[:, None]
    offset = aperture * (lens_point[0] * R_t[0] + lens_point[1] * R_t[1])  # camera x (right), y (down)
    lens_origin = origin + offset
    new_directions = focal_points - lens_origin
    return lens_origin.expand_as(new_directions), new_directions / new_directions.norm(dim=1, keepdim=True)
