"""Camera rays in the scene's world frame.

Two sources, one convention (COLMAP: x right, y down, z forward, pixel centres at +0.5):
- `view_rays`: any pycolmap camera model; directions come from the model's own
  unprojection, so a distorted photo's pixels get their true rays.
- `pinhole_rays`: an undistorted pinhole given by K (what Blender cameras and the render
  API use), computed in torch on the render device so rendering never leaves it.
"""

from __future__ import annotations

import numpy as np
import pycolmap
import torch


def pixel_centres(width: int, height: int) -> np.ndarray:
    """(H*W, 2) pixel centre coordinates, row-major from the top-left corner."""
    xs = np.arange(width, dtype=np.float64) + 0.5
    ys = np.arange(height, dtype=np.float64) + 0.5
    grid_x, grid_y = np.meshgrid(xs, ys)
    return np.stack([grid_x.ravel(), grid_y.ravel()], axis=1)


def view_rays(camera: pycolmap.Camera, R: np.ndarray, t: np.ndarray, pixels: np.ndarray | None = None):
    """Origin (3,) and unit world directions (N, 3) float64 for `pixels` (default: all, row-major)."""
    if pixels is None:
        pixels = pixel_centres(int(camera.width), int(camera.height))
    bearings = camera.cam_ray_from_img(np.ascontiguousarray(pixels, dtype=np.float64))
    bearings = np.asarray(bearings, dtype=np.float64)
    directions = bearings @ R  # R^T applied to each row: camera frame -> world frame
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return -R.T @ t, directions


def pinhole_rays(K, R, t, width: int, height: int, device="cpu", dtype=torch.float64, rows: slice | None = None):
    """Origin (3,) and unit world directions (N, 3) of a pinhole camera, as torch tensors.

    `rows` limits the rays to a band of image rows (chunked rendering of huge frames).
    """
    K = torch.as_tensor(np.asarray(K, dtype=np.float64), dtype=dtype, device=device)
    R = torch.as_tensor(np.asarray(R, dtype=np.float64), dtype=dtype, device=device)
    t = torch.as_tensor(np.asarray(t, dtype=np.float64), dtype=dtype, device=device)
    row_range = range(height)[rows] if rows is not None else range(height)
    ys = torch.arange(row_range.start, row_range.stop, device=device, dtype=dtype) + 0.5
    xs = torch.arange(width, device=device, dtype=dtype) + 0.5
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    x = (grid_x - K[0, 2] - K[0, 1] * (grid_y - K[1, 2]) / K[1, 1]) / K[0, 0]  # K[0,1]: skew
    y = (grid_y - K[1, 2]) / K[1, 1]
    bearings = torch.stack([x, y, torch.ones_like(x)], dim=-1).reshape(-1, 3)
    directions = bearings @ R
    directions = directions / directions.norm(dim=1, keepdim=True)
    return -R.T @ t, directions


def single_pixel_K(K, x: float, y: float) -> np.ndarray:
    """K of a 1x1 image whose only pixel centre is image point (x, y) of the camera `K`
    (top-left origin: x = 10.5 is the centre of column 10) -- a one-ray render of any pixel."""
    return shifted_K(K, (float(x) - 0.5, float(y) - 0.5))


def shifted_K(K, offset) -> np.ndarray:
    """K whose pixel centres are the image points `offset` pixels (x right, y down) from K's."""
    moved = np.array(K, dtype=np.float64).reshape(3, 3)
    moved[0, 2] -= float(offset[0])
    moved[1, 2] -= float(offset[1])
    return moved


def pinhole_K(camera: pycolmap.Camera) -> np.ndarray:
    """3x3 K of a camera (its distortion ignored)."""
    return np.asarray(camera.calibration_matrix(), dtype=np.float64)
