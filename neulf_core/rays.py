"""Camera rays in the scene's world frame.

Two sources, one convention (COLMAP: x right, y down, z forward, pixel centres at +0.5):
- `view_rays`: any pycolmap camera model; directions come from the model's own
  unprojection, so a distorted photo's pixels get their true rays.
- `pinhole_rays`: an undistorted pinhole given by K (what Blender cameras and the render
  API use), computed in torch on the render device so rendering never leaves it.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np
import pycolmap
import torch

# The bearings last unprojected (`camera_bearings`), by a digest of the camera and the pixels,
# up to this many bytes: a capture's photos mostly share one camera and pixel grid, so the
# training rays of every view, the plane sweep's, and the renders of the held-out views (each
# chunk's points of a pixel) ask for the same bearings again.  pycolmap's iterative
# undistortion is most of a ray's cost there (SIMPLE_RADIAL: 4.6 ms per 32k pixels, a quarter
# of a 480x270 render_view with 4 points a pixel; the digest takes a tenth of that).
BEARINGS_KEPT_BYTES = 128 << 20
_bearings: OrderedDict[bytes, np.ndarray] = OrderedDict()
_bearings_lock = threading.Lock()


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
    directions = camera_bearings(camera, pixels) @ R  # R^T applied to each row: camera frame -> world frame
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return -R.T @ t, directions


def camera_bearings(camera: pycolmap.Camera, pixels: np.ndarray) -> np.ndarray:
    """(N, 3) float64 unit rays, camera frame, of image points `pixels` (N, 2): pycolmap's
    unprojection, or the same array kept from the last time these were asked (read-only)."""
    pixels = np.ascontiguousarray(pixels, dtype=np.float64)
    digest = hashlib.blake2b(pixels.tobytes(), digest_size=16)
    digest.update(f"{camera.model} {int(camera.width)} {int(camera.height)}".encode())
    digest.update(np.asarray(camera.params, dtype=np.float64).tobytes())
    key = digest.digest()
    with _bearings_lock:
        kept = _bearings.get(key)
        if kept is not None:
            _bearings.move_to_end(key)
            return kept
    bearings = np.asarray(camera.cam_ray_from_img(pixels), dtype=np.float64)
    bearings.setflags(write=False)
    if bearings.nbytes <= BEARINGS_KEPT_BYTES:
        with _bearings_lock:
            _bearings[key] = bearings
            while sum(kept.nbytes for kept in _bearings.values()) > BEARINGS_KEPT_BYTES:
                _bearings.popitem(last=False)
    return bearings


def pinhole_rays(K, R, t, width: int, height: int, device="cpu", dtype=torch.float64, rows: slice | None = None):
    """Origin (3,) and unit world directions (N, 3) of a pinhole camera, as torch tensors.

    `rows` limits the rays to a band of image rows (chunked rendering of huge frames).
    """
    row_range = range(height)[rows] if rows is not None else range(height)
    ys = torch.arange(row_range.start, row_range.stop, device=device, dtype=dtype) + 0.5
    xs = torch.arange(width, device=device, dtype=dtype) + 0.5
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return pinhole_rays_at(K, R, t, grid_x.reshape(-1), grid_y.reshape(-1))


def pinhole_rays_at(K, R, t, xs: torch.Tensor, ys: torch.Tensor):
    """Origin (3,) and unit world directions (N, 3) of a pinhole camera's rays through the image
    points (xs, ys) (top-left origin: x = 10.5 is the centre of column 10), on their device."""
    device, dtype = xs.device, xs.dtype
    K = torch.as_tensor(np.asarray(K, dtype=np.float64), dtype=dtype, device=device)
    R = torch.as_tensor(np.asarray(R, dtype=np.float64), dtype=dtype, device=device)
    t = torch.as_tensor(np.asarray(t, dtype=np.float64), dtype=dtype, device=device)
    x = (xs - K[0, 2] - K[0, 1] * (ys - K[1, 2]) / K[1, 1]) / K[0, 0]  # K[0,1]: skew
    y = (ys - K[1, 2]) / K[1, 1]
    bearings = torch.stack([x, y, torch.ones_like(x)], dim=-1)
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
