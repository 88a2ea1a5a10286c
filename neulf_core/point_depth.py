"""Depth from the reconstruction's points: the rays through the training photos' keypoints
get the depth of the 3D point they observe, as DS-NeRF supervises a radiance field's depth
with the structure-from-motion points.

Why: a light field learns depth from the parallax between its photos, and with few photos a
thin structure or a plain surface leaves the depth to chance -- the plane sweep's pull
(teacher.py) fades early, and a seed that loses a depth renders the viewpoints between the
photos wrong there.  The keypoints COLMAP matched are the capture's most reliable depth: a
few thousand rays (1.5 % of CanClip's at 240 x 135) whose depth holds for every viewpoint.
Measured at the stability study's 1000 steps, seeds 0-3 (docs/STABILITY.md, forty-fifth
session): CanClip's 6 photos 34.72 -> 34.95 dB (range over the seeds 0.42 -> 0.12), all 26
photos 36.25 -> 36.44.

Each point is triangulated again from the training photos' observations alone (the
least-squares meeting point of their rays, through the photos' own poses): the model's point
was placed using every photo, held-out ones included, and a point seen by fewer than two
training photos, or from directions less than MIN_ANGLE_DEGREES apart, has no depth to give.
Where the model keeps no tracks (LLFF poses, a model without 2D points) nothing changes.
"""

from __future__ import annotations

import numpy as np
import torch

from .dataset import view_uvst
from .slab import Slab

# The pull toward the points' depth, per point ray, relative to the photometric loss over a
# batch (the loss is POINT_DEPTH_WEIGHT x the mean over the batch of |unit depth - target|
# on the point rays, 0 on the others).  At 1000 steps on CanClip's 6 photos, seeds 0-3:
# 0.25 / 0.5 / 1 / 2 -> 34.96 / 34.98 / 34.92 / 34.86 dB (34.72 without).
POINT_DEPTH_WEIGHT = 0.5
# Rays that meet at a smaller angle place their point too loosely along them.
MIN_ANGLE_DEGREES = 1.0


def triangulate(views) -> dict[int, np.ndarray]:
    """{point id: world position} of every point at least two of `views` observe from
    directions at least MIN_ANGLE_DEGREES apart: the point nearest all their rays."""
    ids, centres, directions = [], [], []
    for view in views:
        if view.keypoints is None or not len(view.keypoints):
            continue
        normalised = np.asarray(view.camera.cam_from_img(view.keypoints), dtype=np.float64)
        rays = np.concatenate([normalised, np.ones((len(normalised), 1))], axis=1) @ view.R  # R^T per row
        directions.append(rays / np.linalg.norm(rays, axis=1, keepdims=True))
        centres.append(np.repeat(view.center[None], len(rays), axis=0))
        ids.append(view.point_ids)
    if not ids:
        return {}
    ids, centres, directions = np.concatenate(ids), np.concatenate(centres), np.concatenate(directions)
    unique, slot = np.unique(ids, return_inverse=True)
    counts = np.bincount(slot, minlength=len(unique))
    # Least squares: sum_i (I - d_i d_i^T) (X - C_i) = 0 over the point's rays.
    projectors = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]
    lhs = np.zeros((len(unique), 3, 3))
    rhs = np.zeros((len(unique), 3))
    np.add.at(lhs, slot, projectors)
    np.add.at(rhs, slot, np.einsum("nij,nj->ni", projectors, centres))
    mean_direction = np.zeros((len(unique), 3))
    np.add.at(mean_direction, slot, directions)
    mean_direction /= np.maximum(np.linalg.norm(mean_direction, axis=1, keepdims=True), 1e-12)
    # The widest pair of rays is at least the widest ray's angle from their mean direction.
    off_mean = np.degrees(np.arccos(np.clip((directions * mean_direction[slot]).sum(1), -1.0, 1.0)))
    widest = np.zeros(len(unique))
    np.maximum.at(widest, slot, off_mean)
    usable = (counts >= 2) & (widest >= MIN_ANGLE_DEGREES / 2)
    positions = np.linalg.solve(lhs[usable], rhs[usable][:, :, None])[:, :, 0]
    return dict(zip(unique[usable].tolist(), positions))


def point_depth_targets(train_views, slab: Slab, scale: float,
                        representable=None) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(unit depth, mask) per training ray in build_rayset's order (views in turn, row-major
    pixels, the rays that cross the slab: `representable`, build_rayset's masks of them, or
    traced again where None): the depth of the point a ray's pixel observes,
    where it observes one the training photos triangulate in front of the slab's depth range;
    None where no training ray does."""
    points = triangulate(train_views)
    if not points:
        return None
    units, masks = [], []
    for i, view in enumerate(train_views):
        camera = view.scaled_camera(scale)
        width, height = int(camera.width), int(camera.height)
        unit = torch.zeros(width * height)
        mask = torch.zeros(width * height, dtype=torch.bool)
        pixels, xyz = _keypoint_pixels(view, points, width, height)
        if len(xyz):
            depth = torch.as_tensor(slab.to_slab(xyz)[:, 2])
            target = slab.unit_from_depth(depth.clamp_min(1e-9)).float()
            keep = (depth > 0) & (target >= 0) & (target <= 1)  # in front, inside the slab's depth range
            unit[pixels[keep]] = target[keep]
            mask[pixels[keep]] = True
        valid = representable[i] if representable is not None else view_uvst(view, slab, scale)[1]
        valid = torch.as_tensor(valid).reshape(-1)
        units.append(unit[valid])
        masks.append(mask[valid])
    mask = torch.cat(masks)
    return (torch.cat(units), mask) if bool(mask.any()) else None


def _keypoint_pixels(view, points: dict[int, np.ndarray], width: int, height: int) -> tuple[torch.Tensor, np.ndarray]:
    """(row-major pixel index at the training size, point position) of each of `view`'s
    keypoints whose point is in `points` and whose pixel is inside the frame (COLMAP's pixel
    (0, 0) spans 0..1)."""
    if view.keypoints is None:
        return torch.zeros(0, dtype=torch.long), np.zeros((0, 3))
    known = np.array([pid in points for pid in view.point_ids.tolist()], dtype=bool)
    xy = view.keypoints[known] * np.array([width / view.camera.width, height / view.camera.height])
    column, row = np.floor(xy[:, 0]).astype(int), np.floor(xy[:, 1]).astype(int)
    inside = (column >= 0) & (column < width) & (row >= 0) & (row < height)
    xyz = np.array([points[pid] for pid in view.point_ids[known][inside].tolist()]).reshape(-1, 3)
    return torch.as_tensor(row[inside] * width + column[inside], dtype=torch.long), xyz


def point_depth_loss(unit: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """POINT_DEPTH_WEIGHT x the batch mean of |unit - target| over its point rays (0 elsewhere)."""
    return POINT_DEPTH_WEIGHT * (mask.float() * (unit.reshape(-1) - target).abs()).mean()
