"""Camera paths inside the light field's valid region (for videos and previews).

The spiral follows LLFF/NeRF's render path: an ellipse through the camera rig in the
slab's xy plane (radii from the spread of the capture's camera centres), a gentle
forward-backward motion, every frame looking at the centre of the st plane.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from .errors import NeulfError
from .slab import Slab


# A rig whose cameras stand within this fraction of the st plane's depth of each other has no
# baseline: its light field holds the views from one place only (train.has_baseline).
NO_BASELINE_FRACTION = 1e-6
STILL_SPIRAL = ("the capture's cameras all stood at one place (a tripod panorama, or one photo many times): a light "
                "field of it shows the scene from there only, so every frame of the spiral is the same view; take the "
                "photos from positions a little apart for a path to fly through")


def rig_has_baseline(slab: Slab, camera_centres: np.ndarray) -> bool:
    """Whether the cameras stand apart by more than NO_BASELINE_FRACTION of the scene's depth."""
    local = slab.to_slab(np.asarray(camera_centres, np.float64).reshape(-1, 3))
    return float(np.ptp(local, axis=0).max()) > NO_BASELINE_FRACTION * slab.z_st


def look_at(position: np.ndarray, target: np.ndarray, down_hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a COLMAP-convention camera at `position` looking at `target`."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(down_hint, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ position


def spiral_path(slab: Slab, camera_centres: np.ndarray, frames: int = 60, rotations: float = 1.0,
                radius_fraction: float = 0.8) -> list[tuple[np.ndarray, np.ndarray]]:
    """`frames` world-to-camera poses on an ellipse inside the capture's camera spread."""
    local = slab.to_slab(camera_centres)
    radii = np.percentile(np.abs(local - local.mean(0)), 90, axis=0) * radius_fraction
    centre = local.mean(0)
    target = slab.to_world(np.array([[0.0, 0.0, slab.z_st]]))[0]
    down = slab.rotation[1]
    poses = []
    for angle in np.linspace(0.0, 2 * np.pi * rotations, frames, endpoint=False):
        offset = np.array([np.cos(angle) * radii[0], np.sin(angle) * radii[1], np.sin(angle / 2) * radii[2]])
        position = slab.to_world((centre + offset)[None])[0]
        poses.append(look_at(position, target, down))
    return poses


NO_RIG = "this model has no saved camera rig; retrain it with this version"


def saved_rig(meta: dict) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The capture's camera rig a model keeps (its metadata's "rig"): the camera centres (N x 3),
    the pinhole K (3 x 3), width and height -- what a camera path is flown with; a NeulfError
    where it is missing or damaged (it had failed in int() or numpy with their own words)."""
    rig = meta.get("rig")
    if not rig:
        raise NeulfError(f"{NO_RIG}.")
    try:
        centres = np.asarray(rig["centres"], dtype=np.float64)
        K = np.asarray(rig["K"], dtype=np.float64)
        width, height = (int(rig[key]) for key in ("width", "height"))
        sound = (centres.ndim == 2 and centres.shape[1] == 3 and len(centres) > 0 and K.shape == (3, 3)
                 and np.isfinite(centres).all() and np.isfinite(K).all() and width > 0 and height > 0)
    except (KeyError, TypeError, ValueError, OverflowError, AttributeError):
        sound = False
    if not sound:
        raise NeulfError("this model's camera rig (its capture's cameras, kept for camera paths) is damaged; retrain "
                         "the model, or restore its folder from a backup.")
    return centres, K, width, height


# ----------------------------------------------------------------------------- what a path's frames see

# Frames are checked on an image this many pixels wide: a coarse grid is enough to count the
# share of a frame's rays that leave the captured region, and 60 frames take milliseconds.
PATH_CHECK_WIDTH = 64
# A longer path is checked at this many frames spread evenly along it (a spiral turns smoothly;
# `video --frames 100000` had spent minutes on the check before its first frame).
PATH_CHECK_FRAMES = 240
# The longest lens (times the given focal length) looked for to keep a path inside the capture.
LONGEST_LENS_FACTOR = 16.0


def share_past_capture(slab: Slab, K, width: int, height: int, poses) -> np.ndarray:
    """For each (R, t) in `poses`, the share of the camera's rays (of those that face the slab)
    whose (u, v, s, t) lie past the region the photos captured, counted as the renderer counts
    them for its warning (render.EXTRAPOLATION_MARGIN), on a grid PATH_CHECK_WIDTH wide."""
    import torch

    from .rays import pinhole_rays
    from .render import EXTRAPOLATION_MARGIN

    grid = min(1.0, PATH_CHECK_WIDTH / width)
    small_K = np.array(K, np.float64).reshape(3, 3)
    small_K[:2] *= grid  # (focal lengths, skew and principal point: the same view, fewer pixels)
    small_width, small_height = max(1, round(width * grid)), max(1, round(height * grid))
    local = replace(slab, origin=np.zeros(3))  # (rays relative to the slab's origin, as the renderer makes them)
    shares = []
    for R, t in poses:
        origin, directions = pinhole_rays(small_K, R, slab.origin_relative_t(R, t), small_width, small_height,
                                          dtype=torch.float32)
        uvst, valid = local.rays_to_uvst(origin, directions)
        past = (uvst.abs() > 1 + EXTRAPOLATION_MARGIN).any(dim=1) & valid
        shares.append(float(past.sum()) / max(1, int(valid.sum())))
    return np.array(shares)


def _spread_along(poses: list, count: int) -> list:
    """At most `count` of `poses`, evenly spaced along the path, the first and last included."""
    if len(poses) <= count:
        return poses
    return [poses[i] for i in np.linspace(0, len(poses) - 1, count).round().astype(int)]


def lens_keeping_inside(slab: Slab, K, width: int, height: int, poses, share: float) -> float | None:
    """The smallest factor (to 1 %) by which the focal length of `K` must grow for no frame of
    `poses` to see more than `share` of its rays past the capture: 1.0 where none does already,
    None where not even LONGEST_LENS_FACTOR does (the positions themselves lie past it)."""

    def inside(factor: float) -> bool:
        longer = np.array(K, np.float64).reshape(3, 3)
        longer[0, :2] *= factor  # (focal length and skew: a longer lens on the same sensor)
        longer[1, 1] *= factor
        return bool(share_past_capture(slab, longer, width, height, poses).max() <= share)

    if inside(1.0):
        return 1.0
    if not inside(LONGEST_LENS_FACTOR):
        return None
    short, long = 1.0, LONGEST_LENS_FACTOR
    while long / short > 1.01:  # (a narrower view sees less past the edges: the share falls as the lens grows)
        middle = math.sqrt(short * long)
        short, long = (short, middle) if inside(middle) else (middle, long)
    return long


def past_capture_warning(slab: Slab, K, width: int, height: int, poses, lens_mm: float | None = None) -> str | None:
    """A warning where frames of `poses` through the camera `K` (width x height) see more than
    render.PAST_CAPTURE_FRACTION of their rays past the captured region, else None.  Given the
    camera's focal length in mm (Blender's lens), it names the lens that keeps every frame inside."""
    from .render import PAST_CAPTURE_FRACTION

    poses = list(poses)
    checked = _spread_along(poses, PATH_CHECK_FRAMES)
    shares = share_past_capture(slab, K, width, height, checked)
    past = shares > PAST_CAPTURE_FRACTION
    if not past.any():
        return None
    count = (f"{int(past.sum())}" if len(checked) == len(poses) else
             f"about {max(1, round(float(past.mean()) * len(poses)))}")
    note = (f"{count} of {len(poses)} frames look past the region the photos captured (up to "
            f"{shares.max():.0%} of a frame): what they show there is the light field's guess")
    if lens_mm is None:
        return note
    factor = lens_keeping_inside(slab, K, width, height, checked, PAST_CAPTURE_FRACTION)
    if factor is None:
        return note + (f"; not even a lens {LONGEST_LENS_FACTOR:g} times as long keeps them inside: the path "
                       "passes places the photos did not see")
    return note + f"; a lens of {math.ceil(lens_mm * factor)} mm or longer (this camera's: {lens_mm:g} mm) keeps every frame inside"
