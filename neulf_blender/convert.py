"""Blender <-> COLMAP cameras: intrinsics, poses, the root empty's scale.  numpy only.

COLMAP: x right, y down, z forward, world-to-camera (R, t), pixel centres at +0.5 from
the top-left corner.  Blender: the camera looks down its local -z with +y up, and its
intrinsics are lens, sensor, sensor fit, shift, and the scene's resolution and pixel
aspect.  The formulas are exact both ways (see docs in BLENDER_NOTES): a pinhole K set on a
Blender camera comes back to within float rounding.
"""

from __future__ import annotations

import math

import numpy as np

from ..neulf_core.errors import NeulfError
from ..neulf_core.exr import NO_DEPTH, depth_for_compositing, srgb_to_linear  # noqa: F401 (the extension's)

FLIP = np.diag([1.0, -1.0, -1.0, 1.0])  # COLMAP camera axes <-> Blender camera axes
SENSOR_WIDTH = 36.0


def blender_camera_from_K(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> dict:
    """Camera and render settings that reproduce a pinhole K at width x height."""
    ax, ay = (fy / fx, 1.0) if fy >= fx else (1.0, fx / fy)
    return {
        "resolution_x": int(width), "resolution_y": int(height), "resolution_percentage": 100,
        "pixel_aspect_x": float(ax), "pixel_aspect_y": float(ay),
        "sensor_fit": "HORIZONTAL", "sensor_width": SENSOR_WIDTH,
        "lens": float(fx) * SENSOR_WIDTH / width,
        "shift_x": (width / 2.0 - cx) / width,
        "shift_y": (cy - height / 2.0) / (width * ax / ay),
    }


def render_size(resolution_x: int, resolution_y: int, percentage: int) -> tuple[int, int]:
    """The rendered image size in pixels, as Blender computes it."""
    return int(resolution_x * percentage / 100), int(resolution_y * percentage / 100)


def border_region(width: int, height: int, border_x: tuple[float, float],
                  border_y: tuple[float, float]) -> tuple[int, int, int, int]:
    """The pixels a render region (Output > Format > Render Region) renders, as Blender cuts
    them (each edge truncated to a whole pixel; the y fractions count from the bottom):
    (left, top, width, height) with a top-left origin."""
    left, right = int(border_x[0] * width), int(border_x[1] * width)
    bottom, top = int(border_y[0] * height), int(border_y[1] * height)
    return left, height - top, right - left, top - bottom


def crop_request(request: dict, left: int, top: int, width: int, height: int) -> dict:
    """A render request for the pixels of `request`'s image from (left, top), `width` x `height`:
    the same camera with its principal point moved, so each pixel sees the ray it saw."""
    K = [list(row) for row in request["K"]]
    K[0][2] -= left
    K[1][2] -= top
    return dict(request, K=K, width=width, height=height)


def K_from_blender(*, lens: float, sensor_width: float, sensor_height: float, sensor_fit: str, shift_x: float,
                   shift_y: float, width: int, height: int, pixel_aspect_x: float = 1.0,
                   pixel_aspect_y: float = 1.0) -> np.ndarray:
    """3x3 pinhole K (top-left origin, pixel centres at +0.5) of a Blender camera rendering
    width x height pixels."""
    ax, ay = pixel_aspect_x, pixel_aspect_y
    fit = sensor_fit
    if fit == "AUTO":
        sensor = sensor_width
        fit = "HORIZONTAL" if width * ax >= height * ay else "VERTICAL"
    else:
        sensor = sensor_width if fit == "HORIZONTAL" else sensor_height
    viewfac = width if fit == "HORIZONTAL" else height * ay / ax
    fx = lens / sensor * viewfac
    fy = fx * ax / ay
    cx = width / 2.0 - shift_x * viewfac
    cy = height / 2.0 + shift_y * viewfac * ax / ay
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _viewplane(winx: float, winy: float, aspx: float, aspy: float, *, sensor_fit: str, zoom: float = 1.0,
               shift_x: float = 0.0, shift_y: float = 0.0, offset_x: float = 0.0, offset_y: float = 0.0):
    """Blender's view plane (BKE_camera_params_compute_viewplane) up to the factor
    sensor * clip_start / lens (or ortho_scale), which both planes of a camera view share."""
    ycor = aspy / aspx
    fit = sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if aspx * winx >= aspy * winy else "VERTICAL"
    viewfac = winx if fit == "HORIZONTAL" else ycor * winy
    pixsize = zoom / viewfac
    dx = shift_x * viewfac + winx * offset_x
    dy = shift_y * viewfac + winy * offset_y
    return ((-0.5 * winx + dx) * pixsize, (-0.5 * ycor * winy + dy) * pixsize,
            (0.5 * winx + dx) * pixsize, (0.5 * ycor * winy + dy) * pixsize)


def camera_view_border(region_width: int, region_height: int, *, view_camera_zoom: float,
                       view_camera_offset: tuple[float, float], sensor_fit: str, shift_x: float, shift_y: float,
                       resolution_x: int, resolution_y: int, pixel_aspect_x: float = 1.0,
                       pixel_aspect_y: float = 1.0) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of the camera frame in a viewport looking through the camera,
    in region pixels (origin bottom-left), as Blender draws it (ED_view3d_calc_camera_border).

    The viewport's plane is the camera's own, scaled by the view zoom and moved by the view
    offset; the frame is the render's plane (resolution and pixel aspect) inside it."""
    fac = (math.sqrt(2.0) + view_camera_zoom / 50.0) ** 2 / 4.0   # BKE_screen_view3d_zoom_to_fac
    view = _viewplane(region_width, region_height, 1.0, 1.0, sensor_fit=sensor_fit, zoom=1.0 / fac,
                      shift_x=shift_x * fac, shift_y=shift_y * fac, offset_x=2.0 * view_camera_offset[0] * fac,
                      offset_y=2.0 * view_camera_offset[1] * fac)
    frame = _viewplane(resolution_x, resolution_y, pixel_aspect_x, pixel_aspect_y, sensor_fit=sensor_fit,
                       shift_x=shift_x, shift_y=shift_y)
    width, height = view[2] - view[0], view[3] - view[1]
    return ((frame[0] - view[0]) / width * region_width, (frame[1] - view[1]) / height * region_height,
            (frame[2] - view[0]) / width * region_width, (frame[3] - view[1]) / height * region_height)


def border_to_pixel(border, x: float, y: float, width: int, height: int) -> tuple[float, float] | None:
    """Image point (pixels from the top-left corner) under region point (x, y) (from the
    bottom-left), or None outside the camera frame `border`."""
    xmin, ymin, xmax, ymax = border
    u, v = (x - xmin) / (xmax - xmin), (ymax - y) / (ymax - ymin)
    if not (0.0 <= u <= 1.0 and 0.0 <= v <= 1.0):
        return None
    return u * width, v * height


def matrix_from_pose(R, t) -> np.ndarray:
    """A Blender camera's 4x4 matrix (in the COLMAP world frame) from world-to-camera R, t."""
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    C = np.eye(4)
    C[:3, :3] = R.T
    C[:3, 3] = -R.T @ t
    return C @ FLIP


# How far a camera's normalised axes may be from perpendicular (their dot products) before its
# matrix counts as sheared: float32 matrices of turned, evenly scaled parents stay below 1e-6.
SHEAR_TOLERANCE = 1e-4


def pose_from_matrix(matrix) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) from a camera's 4x4 matrix in the COLMAP world frame.

    Any scale in the matrix (a scaled root empty) is removed from the rotation; the
    position is kept as it is, in model units."""
    M = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    C = M @ FLIP
    axes = C[:3, :3] / np.linalg.norm(C[:3, :3], axis=0)
    if np.abs(axes.T @ axes - np.eye(3)).max() > SHEAR_TOLERANCE:
        # Blender renders such a camera through its normalised, non-orthogonal axes, which no
        # pinhole's rotation is: the nearest rotation had rendered 23 px off Cycles, without a word.
        raise ValueError("the camera's matrix is sheared (a parent scaled unevenly and turned): no pinhole sees what "
                         "Blender's camera does; apply the parent's scale (Ctrl+A > Scale) or clear its parent keeping "
                         "the transform (Alt+P).")
    u, _, vt = np.linalg.svd(C[:3, :3])
    rotation = u @ vt  # nearest rotation: drops scale (and numerical shear)
    if np.linalg.det(rotation) < 0:
        raise ValueError("the camera's matrix is mirrored (negative scale); cameras and the root need positive scale.")
    R = rotation.T
    return R, -R @ C[:3, 3]


def first_scene_camera(sizes, centres) -> int:
    """The photo whose camera a first import makes the scene's: the one nearest the rig's middle
    among the photos of the most common size (a minority portrait photo had made a landscape
    capture's scene, and its video, portrait)."""
    common = max(set(map(tuple, sizes)), key=[tuple(s) for s in sizes].count)
    centres = np.asarray(centres, dtype=np.float64)
    distance = np.linalg.norm(centres - centres.mean(0), axis=1)
    return min((i for i, size in enumerate(sizes) if tuple(size) == common), key=lambda i: distance[i])


def refuse_uneven_scale(root_matrix) -> None:
    """A light field can be moved, turned and scaled as a whole, not stretched: a root scaled
    unevenly (say (1, 1, 2)) had rendered 18 pixels off Blender's own projection, without a word."""
    stretch = np.linalg.svd(np.asarray(root_matrix, dtype=np.float64).reshape(4, 4)[:3, :3], compute_uv=False)
    if stretch[0] > stretch[-1] * (1 + 1e-4):
        raise NeulfError(f"the capture's root is scaled unevenly (its axes scaled {', '.join(f'{s:.4g}' for s in stretch)}); "
                         "a light field can only be scaled the same along every axis: give the root one scale for all "
                         "three (or scale the objects around it instead).")


def uniform_scale(matrix) -> float:
    """The uniform scale of a 4x4 matrix (cube root of the 3x3 determinant)."""
    M = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
    return float(abs(np.linalg.det(M[:3, :3])) ** (1.0 / 3.0))


def image_rows_for_blender(rgb: np.ndarray, alpha: float | np.ndarray = 1.0) -> np.ndarray:
    """(H, W, 3) top-row-first, and an alpha (a number, or (H, W) top-row-first) -> flat float32
    RGBA bottom-row-first (Blender's pixel order)."""
    height, width = rgb.shape[:2]
    rgba = np.empty((height, width, 4), np.float32)
    rgba[..., :3] = rgb[::-1]
    rgba[..., 3] = alpha if np.isscalar(alpha) else np.asarray(alpha)[::-1]
    return rgba.ravel()


def depth_rows_for_blender(depth: np.ndarray) -> np.ndarray:
    """(H, W) depth along the view axis, top-row-first, NaN where the light field has none ->
    flat float32 bottom-row-first for a Z pass, NaN as Cycles' empty pixels (NO_DEPTH)."""
    return depth_for_compositing(depth)[::-1].ravel()
