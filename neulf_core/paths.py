"""Camera paths inside the light field's valid region (for videos and previews).

The spiral follows LLFF/NeRF's render path: an ellipse through the camera rig in the
slab's xy plane (radii from the spread of the capture's camera centres), a gentle
forward-backward motion, every frame looking at the centre of the st plane.
"""

from __future__ import annotations

import numpy as np

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
