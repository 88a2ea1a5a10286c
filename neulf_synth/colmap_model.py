"""Writes the ground truth as a binary COLMAP model, so tests and demos can skip SfM.

pycolmap 4.x models carry rigs and frames: each camera gets a trivial rig (one sensor)
and each image a trivial frame holding its pose. All views share one PINHOLE camera.
The 3D points are sampled from the ground-truth depth of a few views; they have no
tracks (no 2D observations), which is enough to give the scene's extent and colours.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from .cameras import backproject

CAMERA_ID = 1


def pinhole_camera(K: np.ndarray, width: int, height: int) -> pycolmap.Camera:
    return pycolmap.Camera(model="PINHOLE", width=width, height=height,
                           params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=CAMERA_ID)


def sample_points(K, R, t, depth: np.ndarray, image: np.ndarray, count: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """World points and their colours at `count` random pixel centres with finite depth."""
    rows, cols = np.nonzero(np.isfinite(depth))
    pick = rng.choice(len(rows), size=min(count, len(rows)), replace=False)
    rows, cols = rows[pick], cols[pick]
    pixels = np.column_stack([cols + 0.5, rows + 0.5])
    points = backproject(K, R, t, pixels, depth[rows, cols].astype(np.float64))
    return points, image[rows, cols]


def write_model(model_dir: Path, views: list[dict], point_sources: list[tuple],
                points_per_view: int, seed: int) -> pycolmap.Reconstruction:
    """Write `views` (dicts with name, K, R, t, width, height) and sampled points.

    `point_sources` holds (view, depth, image) triples to sample 3D points from.
    """
    first = views[0]
    if any(not np.allclose(view["K"], first["K"], rtol=0, atol=1e-12) for view in views):
        raise ValueError("the ground-truth model shares one camera, but the views' K differ")
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(
        pinhole_camera(np.asarray(first["K"]), first["width"], first["height"]))
    for image_id, view in enumerate(views, start=1):
        image = pycolmap.Image(name=view["name"], camera_id=CAMERA_ID, image_id=image_id)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(view["R"])), np.asarray(view["t"]))
        reconstruction.add_image_with_trivial_frame(image, pose)
    rng = np.random.default_rng([seed, 3])
    for view, depth, image in point_sources:
        points, colors = sample_points(np.asarray(view["K"]), np.asarray(view["R"]),
                                       np.asarray(view["t"]), depth, image, points_per_view, rng)
        for xyz, color in zip(points, colors):
            reconstruction.add_point3D(xyz, pycolmap.Track(), color.astype(np.uint8))
    model_dir.mkdir(parents=True, exist_ok=True)
    reconstruction.write_binary(str(model_dir))
    return reconstruction
