"""Rendering a trained light field for any camera: RGB and depth, in bounded-memory chunks.

One code path serves the CLI, evaluation, the benchmark and the Blender layer: rays of a
camera -> (u, v, s, t) through the slab -> the field, `chunk` rays at a time, on the
model's device.  Depth is the distance along the camera's optical axis in scene units.
"""

from __future__ import annotations

import math
import numbers

from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pycolmap
import torch

from .checkpoint import load_for_render
from .device import HALF_DEVICES, keep_freed_cpu_memory, pick_device, release_cached_memory
from .errors import NeulfError, is_out_of_memory
from .fields import build_field, make_config
from .fields import depth_unit as field_depth_unit
from .images import LARGEST_IMAGE_SIDE
from .members import finished_members, member_dir
from .rays import pinhole_K, pinhole_rays, pinhole_rays_at, pixel_centres, shifted_K, single_pixel_K, view_rays
from .refocus import MAX_SAMPLES, lens_rays, lens_samples, max_blur_radius_px, sample_count
from .scene import View
from .slab import Slab
from .trained_scene import other_reconstruction

# Rays per chunk.  On a CPU a chunk's intermediates (a few MB) stay in cache and are reused
# by the allocator: with 1 thread, 16k-32k rays rendered the default field about 10% faster
# than 8k or 64k (docs/BENCHMARKS.md); more threads want the larger.  A GPU wants large
# chunks: a frame's time there is mostly kernel launches and host work, not arithmetic.  On an
# H200 at 1008x567 (571,536 rays) the default field rendered 4.8 ms per frame with 2^20 rays
# per chunk against 9.2 ms with 2^18 (5.8 / 10.8 ms with depth), peak GPU memory 438 MiB
# (benchmarks/render_fps.py --chunks, docs/BENCHMARKS.md).  A chunk the device has no memory
# for is retried in halves (`in_chunks`), so small GPUs render too.
DEFAULT_CHUNK = 1 << 15
ACCELERATOR_CHUNK = 1 << 20
# Rays whose (u, v, s, t) lie this far outside the trained range are extrapolation.
EXTRAPOLATION_MARGIN = 0.1
# A render is said to leave the captured region where more of its rays than this do.
PAST_CAPTURE_FRACTION = 0.05
# Field evaluation precision.  "half" runs the field's matrix products in float16 under
# autocast (tensor cores on a GPU); ray geometry, (u, v, s, t) and the texture reads stay
# float32, and the disparity field keeps its geometry branch in float32 (fields/disparity.py).
# Measured on CPU against float32 (CanClip, 2000-step default field, one view at 480x270):
# colours 78 dB apart, depth identical; autocast over the whole render instead (ray
# directions in float16 too) put them 47 dB apart with depth 2 % off.  "auto" is half on
# CUDA only: on a CPU float16 products are slower, not faster ("half" there is for checking
# the numbers).  Scores (eval, the auto preset's validation) render in "full".
PRECISIONS = ("auto", "half", "full")
# Points per pixel of a finished render (`pixel_samples`): the colour is the mean of the field
# over a square grid of points in each pixel -- the light a pixel gathers over its area, which
# is what a photo's pixel records.  The field is trained on the rays through the photos' pixel
# centres; a new camera's centre rays fall between them in ray space, where the field carries
# detail finer than a pixel that no photo constrains, and the mean over the pixel averages it
# out.  The points are the cell centres of a grid over the pixel's central PIXEL_FOOTPRINT x
# PIXEL_FOOTPRINT square: spread wider the mean also blurs, which costs a field that is already
# sharp (HCI's 70 views: -0.48 dB over the whole pixel at 1000 steps, -0.20 over 0.75 of it at
# 3000), while over half of it no model lost.  Measured on held-out views
# (benchmarks/pixel_samples.py, docs/PIXEL_SAMPLES.md), 4 points against 1: +0.05 dB (Statue) to
# +0.28 dB (CanClip's 6 photos at 3000 steps), in every model, higher SSIM, at 4 times the field
# queries (5 with depth: the centre ray's); blurring the one-point render instead loses up to
# 1.5 dB on CanClip.
PIXEL_SAMPLES = (1, 4, 9, 16)
DEFAULT_PIXEL_SAMPLES = 4
# ... except where a render is this many times finer than the photos the model trained on (its
# focal length in pixels against theirs: Blender renders a camera at its photo's full size from a
# model trained at the scale rule's smaller one): there the default takes the centre ray alone.
# A render pixel that small falls inside one trained pixel, and the points over it gained +0.014
# dB on average at 1.5 times (8 models) and +0.001 dB at 2 times (18 models: three seeds of five
# scenes, one of three), for 1.6 to 5 times one point's render time; at the trained size they gain
# +0.10 dB (benchmarks/sample_contrast.py --render-scale F, docs/PIXEL_SAMPLES.md, 2026-12-07).
FINE_RENDER_SCALE = 1.5
PIXEL_FOOTPRINT = 0.5
# Which pixels take the points (`sample_contrast`): only those whose centre-ray colour differs
# from a neighbour's (left, right, above, below) by more than this in some channel (colours 0-1;
# 0.02 is 5 of 255 levels); the others keep the centre ray's colour.  The gain of the points is
# at edges and fine texture: where the picture is flat, the mean of the points is the centre's.
# 0 gives every pixel the points.  Measured on held-out views at the trained size, eight models
# (docs/PIXEL_SAMPLES.md, "Points where the picture has contrast"): all but 0.004 dB of the
# points' gain on average (HCI 0.022); CanClip's, Statue's and HCI's views, 21-34 % of whose
# pixels take them, in about half the time; views with contrast nearly everywhere (the fine
# synthetic textures) 1.2-1.3 times as long, since their centre colours are work the points redo.
SAMPLE_CONTRAST = 0.02


def half_precision(precision: str, device: torch.device) -> bool:
    """Whether the field runs in float16 (see PRECISIONS)."""
    if precision not in PRECISIONS:
        raise NeulfError(f"unknown precision '{precision}'; use one of {', '.join(PRECISIONS)}.")
    if precision == "half" and device.type not in HALF_DEVICES:
        raise NeulfError(f"half precision renders on CUDA (or on the CPU, to check it), not on {device.type}; "
                         "use --precision full or auto.")
    return precision == "half" or (precision == "auto" and device.type == "cuda")


def in_chunks(total: int, size: int, run) -> int:
    """Call `run(start, stop)` over [0, total) in pieces of `size`; stop early when it returns
    False.  A piece the device has no memory for is tried again in halves (down to one), and
    the smaller size is kept for the rest: peak memory follows what the device has free.
    Returns where it stopped (`total` when it ran to the end)."""
    start = 0
    while start < total:
        stop = min(total, start + size)
        try:
            carry_on = run(start, stop)
        except Exception as exc:  # noqa: BLE001
            if not is_out_of_memory(exc) or size == 1:
                raise
            size = max(1, size // 2)
            release_cached_memory()  # give the failed piece's blocks back before the smaller try
            continue
        if carry_on is False:
            return stop
        start = stop
    return total


@dataclass
class Rendering:
    rgb: np.ndarray                 # (H, W, 3) float32 in [0, 1]
    depth: np.ndarray | None        # (H, W) float32, along the optical axis; nan where not representable
    valid: np.ndarray               # (H, W) bool: the ray crosses the slab forwards, its surface ahead of the camera
    warnings: list[str] = field(default_factory=list)
    complete: bool = True           # False where `on_chunk` stopped it: the rows below hold no picture
    refined: float = 0.0            # the share of its pixels that took the points (pixel_samples above 1)
    pixel_samples: int = 1          # the points per pixel it was rendered with (default_pixel_samples where None was asked)


def image_size(width, height) -> tuple[int, int]:
    """(width, height) as whole numbers of at least 1 pixel; 80.7 was taken as 80 without a word."""
    try:
        whole = all(not isinstance(v, bool) and float(v).is_integer() for v in (width, height))
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole or int(width) < 1 or int(height) < 1:
        raise NeulfError(f"cannot render a {width!r}x{height!r} image: width and height must be whole numbers of at "
                         "least 1 pixel.")
    if max(int(width), int(height)) > LARGEST_IMAGE_SIDE:
        raise NeulfError(f"cannot render a {width!r}x{height!r} image: a side is at most {LARGEST_IMAGE_SIDE} pixels; "
                         "render a smaller one.")
    return int(width), int(height)


def camera_arrays(K, R, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K (3x3 with positive focal lengths), R (a 3x3 rotation, world to camera) and t (3
    numbers: shape (3,), (3, 1) or (1, 3)) as float64 arrays; what does not fit is refused in
    one line, where it failed deep in torch or rendered a wrong picture without a word."""
    try:
        K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
    except (TypeError, ValueError):
        raise NeulfError("K, R and t must be arrays of numbers (K and R 3x3, t 3 numbers).") from None
    if K.shape != (3, 3) or R.shape != (3, 3) or t.size != 3 or t.ndim > 2:
        raise NeulfError(f"K and R must be 3x3 and t 3 numbers, not shapes {K.shape}, {R.shape} and {t.shape}.")
    t = t.reshape(3)
    if not (np.isfinite(K).all() and np.isfinite(R).all() and np.isfinite(t).all()):
        raise NeulfError("the camera's K, R or t holds NaN or infinity.")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise NeulfError(f"K needs positive focal lengths K[0][0], K[1][1], not {K[0, 0]:g} and {K[1, 1]:g}.")
    if not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise NeulfError(f"K's last row must be [0, 0, 1] (a pinhole's), not {K[2].tolist()}.")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise NeulfError("R is not a rotation (its rows must be unit length, at right angles and right-handed): give "
                         "the world-to-camera rotation, without scale.")
    return K, R, t


class LightField:
    """A trained field with its slab, ready to render."""

    def __init__(self, field_module: torch.nn.Module, slab: Slab, meta: dict, device: torch.device,
                 precision: str = "auto"):
        self.field = field_module.to(device).eval()
        if device.type == "cpu":
            keep_freed_cpu_memory()  # chunks reuse freed buffers instead of page-faulting them in
        self.slab = slab
        self.meta = meta
        self.device = device
        # Ray geometry in float32, as the training rays are (dataset.py): against float64 the
        # colours of CanClip's and fern's held-out views differ by at most 9e-5 and depth by
        # 2e-5 relative, and a frame renders 5-20 % faster on a CPU (docs/BENCHMARKS.md).  Rays
        # are made in the slab's frame moved to the slab's origin (`local_slab`), the camera moved
        # with it in float64 (`Slab.origin_relative_t`): a COLMAP model can sit 1e5-1e7 units from its world's
        # origin (a georeferenced or merged one), where float32 world coordinates are coarser
        # than the camera rig (1e7 off: 19.7 dB where the model scores 28.9; the training rays
        # are made relative to the origin in float64 too, dataset.view_uvst).
        self.geometry_dtype = torch.float32
        self.local_slab = replace(slab, origin=np.zeros(3))
        self.background = torch.tensor(meta.get("scene", {}).get("mean_colour", [0, 0, 0]), dtype=torch.float32, device=device)
        self.half = half_precision(precision, device)

    @classmethod
    def load(cls, model_dir: str | Path, device: str | None = None, precision: str = "auto") -> "LightField":
        """MODEL_DIR/model.pt (float16 weights) when it is current, else checkpoint.pt.
        `precision`: "auto", "half" or "full" (see PRECISIONS)."""
        device = pick_device(device)
        payload = load_for_render(model_dir, map_location="cpu")
        module, slab = _field_and_slab(payload, model_dir)
        meta = {k: v for k, v in payload.items() if k not in ("state_dict", "optimizer", "rng")}
        folder_of_model = Path(model_dir).expanduser()
        others = finished_members(folder_of_model)
        if others:  # an ensemble (members.py): the mean of the members that finished
            fields = [module]
            for member in others:
                folder = member_dir(folder_of_model, member)
                if not folder.is_dir():
                    raise NeulfError(f"{model_dir} is an ensemble of {len(others) + 1} members, but member {member} "
                                     f"({folder}) is missing: put the folder back, or train the model again.")
                field_module, member_slab = _field_and_slab(load_for_render(folder, map_location="cpu"), folder)
                if member_slab.to_dict() != slab.to_dict():
                    raise NeulfError(f"member {member} of {model_dir} was trained with another light slab; "
                                     "train the model again.")
                fields.append(field_module)
            module = MemberMean(fields)
            meta["members"] = [1, *others]
        return cls(module, slab, meta, device, precision)

    @property
    def trained_scale(self) -> float:
        return float(self.meta.get("scene", {}).get("scale", 1.0))

    def check_scene(self, scene) -> None:
        """Registered views can only be rendered in the frame the model was trained in."""
        saved = self.meta.get("scene", {})
        if saved.get("fingerprint") not in (None, scene.fingerprint()):
            # (its light slab lives in that scene's coordinate frame; --cameras in that frame render too)
            raise NeulfError(other_reconstruction(saved, scene, "render and score its views"))

    # ------------------------------------------------------------------ core
    def default_chunk(self) -> int:
        return DEFAULT_CHUNK if self.device.type == "cpu" else ACCELERATOR_CHUNK

    @torch.inference_mode()
    def query(self, origins: torch.Tensor, directions: torch.Tensor, want_depth: bool = True, want_colour: bool = True):
        """Colour (N, 3), camera-independent depth along the slab axis (N,), valid (N,),
        (u, v, s, t) of rays whose `origins` are relative to the slab's origin (`Slab.origin_relative_t`);
        with neither colour nor depth wanted, no field query (colour None)."""
        uvst, valid = self.local_slab.rays_to_uvst(origins, directions)
        if not (want_colour or want_depth):
            return None, None, valid, uvst
        with torch.autocast(self.device.type, dtype=torch.float16) if self.half else nullcontext():
            if want_colour:
                rgb, depth_unit = self.field(uvst.float())
            else:  # (depth alone: the field leaves out its colour's work where it can)
                rgb, depth_unit = None, field_depth_unit(self.field, uvst.float())
        if rgb is not None:
            rgb = torch.where(valid[:, None], rgb.float(), self.background)
        slab_depth = self.slab.depth_from_unit(depth_unit[:, 0].to(self.geometry_dtype)) if want_depth else None
        return rgb, slab_depth, valid, uvst

    def _axis_depth(self, origin: torch.Tensor, directions: torch.Tensor, slab_depth: torch.Tensor, forward: torch.Tensor):
        """Slab-axis depth of the surface point -> distance along the camera's optical axis
        (`origin` relative to the slab's origin)."""
        dtype = self.geometry_dtype
        rotation = torch.as_tensor(self.slab.rotation, device=directions.device, dtype=dtype)
        o_z = origin.to(dtype) @ rotation[2]
        d_z = directions.to(dtype) @ rotation[2]
        ray_length = (slab_depth.to(dtype) - o_z) / d_z
        return ray_length * (directions.to(dtype) @ forward.to(dtype))

    def render(self, K, width: int, height: int, R, t, *, depth: bool = True, chunk: int | None = None,
               on_chunk=None, focus_distance: float | None = None, aperture: float = 0.0,
               max_samples: int = MAX_SAMPLES, pixel_samples: int | None = 1,
               pixel_footprint: float = PIXEL_FOOTPRINT, sample_contrast: float = SAMPLE_CONTRAST) -> Rendering:
        """Render a pinhole camera (K, world-to-camera R, t in the scene's COLMAP frame).

        With `aperture` > 0 (lens radius, scene units) and `focus_distance` (depth along the
        optical axis), the image is refocused by synthetic aperture (see refocus.py); depth
        stays the pinhole ray's.  `pixel_samples` (PIXEL_SAMPLES; None: default_pixel_samples(K)): each pixel's colour the mean
        over that many points of its central `pixel_footprint` square (pixel_offsets), in the
        pixels whose centre-ray colour differs from a neighbour's by more than `sample_contrast`
        (SAMPLE_CONTRAST; 0: in every pixel), the others the centre ray's; depth stays the centre
        ray's (a refocused render's lens samples already spread over the pixel's light, so it
        takes them alone).  A pixel whose surface lies behind the camera (a
        camera inside the scene's depth range) is not valid: the background colour, depth NaN
        (its centre ray decides; a refocused or multi-point pixel's other rays that meet a surface
        behind it count as the background in its mean).
        `on_chunk(rows_done, height)` is called after each band of rows; where it returns False
        the render stops there, and the Rendering says so (`complete` False, a warning)."""
        width, height = image_size(width, height)
        K, R, t = camera_arrays(K, R, t)
        lens = self._lens_plan(K, focus_distance, aperture, max_samples)
        pixel_samples = self.default_pixel_samples(K) if pixel_samples is None else pixel_samples
        offsets = pixel_offsets(pixel_samples, pixel_footprint)  # checked even where the lens takes over
        if lens is not None:
            offsets = pixel_offsets(1)
        spread = len(offsets) > 1
        contrast = contrast_threshold(sample_contrast) if spread else 0.0
        rows_per_chunk = max(1, (chunk or self.default_chunk()) // width)
        forward = torch.as_tensor(R[2], device=self.device, dtype=self.geometry_dtype)
        t_local = self.slab.origin_relative_t(R, t)
        # The field's surfaces lie between the slab's near and far depths: only a camera past the
        # near one can have some behind it, so only there is depth needed to find them.
        inside_scene = self.camera_inside_scene(R, t)
        need_depth = depth or inside_scene
        try:
            rgb_out = np.zeros((height, width, 3), np.float32)  # (rows a stopped render never reached stay empty)
            depth_out = np.full((height, width), np.nan, np.float32) if depth else None
            valid_out = np.zeros((height, width), bool)
        except MemoryError:
            raise NeulfError(f"a {width} x {height} image does not fit in memory ({width * height * 17 / 1e9:.3g} GB "
                             "for its colour, depth and mask): render a smaller one.") from None
        outside = np.zeros(height, np.int64)  # per row: a band retried after running out of memory counts once
        behind = np.zeros(height, np.int64)  # per row: pixels whose surface lies behind the camera
        refined = np.zeros(height, np.int64)  # per row: pixels that took the points (pixel_samples)

        def render_rows(top: int, bottom: int):
            rows = slice(top, bottom)
            # With the points only where the picture has contrast, the centre rays of the rows
            # above and below the band are taken too: a pixel's contrast is with all four of its
            # neighbours, so a band's edge rows are judged as in one whole-frame band.
            halo = slice(max(0, top - 1), min(height, bottom + 1)) if contrast > 0 else rows
            origin, directions = pinhole_rays(K, R, t_local, width, height, self.device, self.geometry_dtype, halo)
            centre_colour = lens is None and (not spread or contrast > 0)  # (else not used)
            rgb, slab_depth, valid, uvst = self.query(origin, directions, need_depth, want_colour=centre_colour)
            axis = self._axis_depth(origin, directions, slab_depth, forward) if need_depth else None
            behind_rays = None
            if inside_scene:
                ahead = axis > 0  # (else the surface this ray's line meets lies behind the camera)
                behind_rays, valid = valid & ~ahead, valid & ahead
            if contrast > 0:
                if inside_scene:
                    rgb = torch.where(valid[:, None], rgb, self.background)
                edges = contrasted_pixels(rgb.reshape(halo.stop - halo.start, width, 3), contrast)
                edges = edges[top - halo.start:bottom - halo.start].reshape(-1)
                band_rays = slice((top - halo.start) * width, (bottom - halo.start) * width)
                directions, uvst, valid, rgb = directions[band_rays], uvst[band_rays], valid[band_rays], rgb[band_rays]
                axis = axis[band_rays] if axis is not None else None
                behind_rays = behind_rays[band_rays] if behind_rays is not None else None
            if inside_scene:
                behind[rows] = behind_rays.reshape(bottom - top, width).sum(1).cpu().numpy()
            facing = forward if inside_scene else None  # (only there can a pixel's other rays meet surfaces behind it)
            if lens is not None:
                rgb = self._refocused_colour(origin, directions, R, focus_distance, aperture, lens, facing)
            elif spread:
                def points(chosen=None):
                    for offset in offsets:
                        if chosen is None:
                            yield pinhole_rays(shifted_K(K, offset), R, t_local, width, height, self.device,
                                               self.geometry_dtype, rows)
                        else:  # (the rays of the chosen pixels alone)
                            yield pinhole_rays_at(shifted_K(K, offset), R, t_local, chosen_x, chosen_y)
                if contrast > 0:
                    chosen = edges.nonzero()[:, 0]
                    if len(chosen):
                        chosen_x = (chosen % width).to(self.geometry_dtype) + 0.5
                        chosen_y = (chosen // width + top).to(self.geometry_dtype) + 0.5
                        rgb = rgb.index_put((chosen,), self._mean_colour(points(chosen), facing))
                    refined[rows] = edges.reshape(bottom - top, width).sum(1).cpu().numpy()
                else:
                    rgb = self._mean_colour(points(), facing)
                    refined[rows] = width
            if inside_scene:
                rgb = torch.where(valid[:, None], rgb, self.background)
            band = bottom - top
            rgb_out[rows] = rgb.reshape(band, width, 3).cpu().numpy()
            valid_out[rows] = valid.reshape(band, width).cpu().numpy()
            outside[rows] = (uvst.abs() > 1 + EXTRAPOLATION_MARGIN).any(dim=1).logical_and(valid).reshape(band, width).sum(1).cpu().numpy()
            if depth:
                axis = torch.where(valid, axis, torch.full_like(axis, math.nan))
                depth_out[rows] = axis.reshape(band, width).float().cpu().numpy()
            return on_chunk(bottom, height) if on_chunk is not None else None

        rows_done = in_chunks(height, rows_per_chunk, render_rows)
        warnings = self._camera_warnings(R, t, valid_out[:rows_done], int(outside.sum()), int(behind.sum()))
        if rows_done < height:
            warnings.append(f"rendering stopped after {rows_done} of {height} rows (on_chunk returned False): the rows "
                            "below hold no picture")
        return Rendering(rgb_out, depth_out, valid_out, warnings, complete=rows_done == height,
                         refined=float(refined[:rows_done].sum()) / max(1, rows_done * width),
                         pixel_samples=len(offsets))

    def _camera_slab_z(self, R, t) -> float:
        """The camera centre's depth along the slab axis (the uv plane at the rig)."""
        return float(self.slab.to_slab((-R.T @ t)[None])[0, 2])

    def camera_inside_scene(self, R, t) -> bool:
        """Whether a camera (world-to-camera R, t) stands past the scene's nearest content, where
        some of what its pixels' lines meet can lie behind it."""
        return self._camera_slab_z(np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3)) > self.slab.z_near

    def _lens_plan(self, K, focus_distance, aperture: float, max_samples: int):
        """Lens sample points for a refocused render, or None for a pinhole one."""
        aperture = 0.0 if aperture is None else aperture
        if not isinstance(aperture, numbers.Real) or not math.isfinite(aperture) or aperture < 0:
            raise NeulfError(f"the aperture (lens radius) must be a finite number of at least 0, not {aperture!r}.")
        if not isinstance(max_samples, numbers.Integral) or isinstance(max_samples, bool) or max_samples < 1:
            raise NeulfError(f"max_samples (lens samples at most) must be a whole number of at least 1, not {max_samples!r}.")
        if aperture == 0:
            return None
        if focus_distance is None or not focus_distance > 0:
            raise NeulfError("refocusing needs a positive focus distance together with the aperture (the CLI: "
                             "--focus-distance D or --focus-pixel X,Y).")
        blur = max_blur_radius_px(float(K[0, 0]), aperture, focus_distance, self.slab.z_near, self.slab.z_far)
        count = sample_count(blur, max_samples)
        return None if count == 1 else lens_samples(count)

    def _mean_colour(self, rays, forward: torch.Tensor | None = None) -> torch.Tensor:
        """The mean colour over bundles of rays (origin, directions), one bundle at a time (a
        pixel's points, or a refocused render's lens samples).  With `forward` (the optical axis
        of a camera inside the scene's depth range) a ray whose surface lies behind the camera
        counts as the background, as a pixel's centre ray does: a lens ray past the edge of a
        foreground object the camera has moved beyond had brought that object's colour into
        the pixels beside it."""
        total, count = None, 0
        for origin, directions in rays:
            if forward is None:
                rgb = self.query(origin, directions, want_depth=False)[0]
            else:
                rgb, slab_depth, valid, _ = self.query(origin, directions)
                behind = valid & (self._axis_depth(origin, directions, slab_depth, forward) <= 0)
                rgb = torch.where(behind[:, None], self.background, rgb)
            total, count = (rgb if total is None else total + rgb), count + 1
        return total / count

    def _refocused_colour(self, origin, directions, R, focus, aperture, lens, forward=None) -> torch.Tensor:
        return self._mean_colour((lens_rays(origin, directions, R, focus, aperture, point) for point in lens), forward)

    def depth_at(self, K, R, t, x: float, y: float) -> float:
        """Depth along the optical axis of the ray through pixel (x, y) (top-left origin, in
        pixels: x = 10.5 is the centre of column 10) -- what auto-refocus focuses on."""
        return picked_depth(float(self.render(single_pixel_K(K, x, y), 1, 1, R, t, depth=True).depth[0, 0]), x, y)

    def _camera_warnings(self, R, t, valid: np.ndarray, outside: int, behind: int = 0) -> list[str]:
        notes = []
        z = self._camera_slab_z(R, t)
        if z > self.slab.z_near:
            notes.append(f"the camera is {z - self.slab.z_near:.3g} units inside the scene's depth range (past the nearest "
                         "content): rays may start behind objects the light field has seen from the front")
        elif z > self.slab.z_uv + 0.5 * (self.slab.z_st - self.slab.z_uv):
            notes.append("the camera is far in front of the uv plane (closer to the st plane than to the capture)")
        if behind:
            notes.append(f"{behind / valid.size:.1%} of the pixels meet what the capture saw behind the camera and show "
                         "the background colour: move the camera back toward the capture positions")
        invisible = int((~valid).sum()) - behind
        if invisible:
            notes.append(f"{invisible / valid.size:.1%} of the pixels look away from the light slab (facing away or "
                         "too oblique) and show the background colour")
        total = int(valid.sum())
        if total and outside / total > PAST_CAPTURE_FRACTION:
            notes.append(f"{outside / total:.0%} of the rays leave the region the cameras captured: "
                         "move the camera closer to the capture positions for reliable results")
        return notes

    def default_pixel_samples(self, K) -> int:
        """Points per pixel where none were asked: DEFAULT_PIXEL_SAMPLES, and 1 where the camera
        K renders FINE_RENDER_SCALE times finer than the photos the model trained on or more."""
        rig = self.meta.get("rig") or {}
        try:
            trained = np.asarray(rig["K"], np.float64)
            finer = math.sqrt(abs(float(K[0][0]) * float(K[1][1])) / abs(float(trained[0, 0]) * float(trained[1, 1])))
        except (KeyError, TypeError, ValueError, IndexError, ZeroDivisionError):  # (a model without its rig's record)
            return DEFAULT_PIXEL_SAMPLES
        return 1 if math.isfinite(finer) and finer >= FINE_RENDER_SCALE else DEFAULT_PIXEL_SAMPLES

    def render_view(self, view: View, scale: float | None = None, *, depth: bool = True, chunk: int | None = None,
                    pixel_samples: int | None = 1, pixel_footprint: float = PIXEL_FOOTPRINT,
                    sample_contrast: float = SAMPLE_CONTRAST, focus_distance: float | None = None,
                    aperture: float = 0.0, max_samples: int = MAX_SAMPLES) -> Rendering:
        """Render a registered view through its own camera model (distortion included), so
        the result lines up pixel for pixel with its photo (`pixel_samples` and `sample_contrast`
        as in `render`).
        With `aperture` and `focus_distance` it is refocused as `render` refocuses, each lens
        sample's rays through the same distorted pixels (a refocus through the view's pinhole
        part had moved CanClip's corners 10 pixels).  The view must be of the scene the model
        was trained on: `check_scene(scene)` says where it is not (the CLI and evaluate_model
        call it)."""
        scale = self.trained_scale if scale is None else scale
        chunk = chunk or self.default_chunk()
        camera: pycolmap.Camera = view.scaled_camera(scale)
        width, height = int(camera.width), int(camera.height)
        pixels = pixel_centres(width, height)
        t_local = self.slab.origin_relative_t(view.R, view.t)
        origin, directions = view_rays(camera, view.R, t_local, pixels)
        origin_t = torch.as_tensor(origin, device=self.device, dtype=self.geometry_dtype)
        forward = torch.as_tensor(view.R[2], device=self.device, dtype=self.geometry_dtype)
        rgb_out = np.empty((len(directions), 3), np.float32)
        valid = np.empty(len(directions), bool)
        depth_map = np.empty(len(directions), np.float32) if depth else None
        K = pinhole_K(camera)
        lens = self._lens_plan(K, focus_distance, aperture, max_samples)
        pixel_samples = self.default_pixel_samples(K) if pixel_samples is None else pixel_samples
        offsets = pixel_offsets(pixel_samples, pixel_footprint)
        if lens is not None:  # (the lens samples spread over each pixel's light: as render)
            offsets = pixel_offsets(1)
        spread = len(offsets) > 1
        contrast = contrast_threshold(sample_contrast) if spread else 0.0

        def moved_rays(chosen):
            for offset in offsets:
                moved = view_rays(camera, view.R, t_local, pixels[chosen] + offset)[1]
                yield origin_t, torch.as_tensor(moved, device=self.device, dtype=self.geometry_dtype)

        inside_scene = self.camera_inside_scene(view.R, view.t)  # (a view moved into the scene: as render does)
        need_depth = depth or inside_scene
        # Per ray, written by index: a chunk retried after running out of memory counts once (summed,
        # the retried chunk's rays were counted twice: "200% of the rays leave the region").
        behind = np.zeros(len(directions), bool)
        outside = np.zeros(len(directions), bool)

        def render_rays(start: int, stop: int):
            d = torch.as_tensor(directions[start:stop], device=self.device, dtype=self.geometry_dtype)
            centre_colour = lens is None and (not spread or contrast > 0)  # (else not used)
            rgb, slab_depth, ok, uvst = self.query(origin_t, d, need_depth, want_colour=centre_colour)
            axis = self._axis_depth(origin_t, d, slab_depth, forward) if need_depth else None
            if inside_scene:
                behind[start:stop] = (ok & (axis <= 0)).cpu().numpy()
                ok = ok & (axis > 0)
            outside[start:stop] = ((uvst.abs() > 1 + EXTRAPOLATION_MARGIN).any(dim=1) & ok).cpu().numpy()
            if lens is not None:
                rgb = self._refocused_colour(origin_t, d, view.R, focus_distance, aperture, lens, facing)
            elif spread and contrast == 0:
                rgb = self._mean_colour(moved_rays(slice(start, stop)), facing)
            if inside_scene:
                rgb = torch.where(ok[:, None], rgb, self.background)
            rgb_out[start:stop] = rgb.cpu().numpy()
            valid[start:stop] = ok.cpu().numpy()
            if depth:
                depth_map[start:stop] = axis.float().cpu().numpy()

        def render_points(start: int, stop: int):  # (the pixels with contrast, after the whole frame's centres)
            chosen = edges[start:stop]
            rgb_out[chosen] = np.where(valid[chosen, None], self._mean_colour(moved_rays(chosen), facing).cpu().numpy(),
                                       self.background.cpu().numpy())

        facing = forward if inside_scene else None
        in_chunks(len(directions), chunk, render_rays)
        refined = 1.0 if spread and contrast == 0 else 0.0
        if contrast > 0:
            centre = torch.as_tensor(rgb_out.reshape(height, width, 3))
            edges = contrasted_pixels(centre, contrast).reshape(-1).nonzero()[:, 0].numpy()
            in_chunks(len(edges), max(1, chunk // len(offsets)), render_points)
            refined = len(edges) / max(1, len(directions))
        valid = valid.reshape(height, width)
        if depth_map is not None:
            depth_map = depth_map.reshape(height, width)
            depth_map[~valid] = np.nan
        return Rendering(rgb_out.reshape(height, width, 3), depth_map, valid,
                         self._camera_warnings(view.R, view.t, valid, int(outside.sum()), int(behind.sum())),
                         refined=refined, pixel_samples=len(offsets))

    def view_depth_at(self, view: View, scale: float | None, x: float, y: float) -> float:
        """Depth along the optical axis under image point (x, y) of a registered view, through its
        own camera model (x = 10.5 the centre of column 10): the depth map render_view gives."""
        camera = view.scaled_camera(self.trained_scale if scale is None else scale)
        origin, direction = view_rays(camera, view.R, self.slab.origin_relative_t(view.R, view.t), np.array([[x, y]]))
        origin_t = torch.as_tensor(origin, device=self.device, dtype=self.geometry_dtype)
        d = torch.as_tensor(direction, device=self.device, dtype=self.geometry_dtype)
        _, slab_depth, ok, _ = self.query(origin_t, d, want_depth=True, want_colour=False)
        forward = torch.as_tensor(view.R[2], device=self.device, dtype=self.geometry_dtype)
        value = float(self._axis_depth(origin_t, d, slab_depth, forward)[0]) if bool(ok[0]) else math.nan
        return picked_depth(value, x, y, f" of {view.name}")


def picked_depth(value: float, x: float, y: float, where: str = "", what_to_do: str = "") -> float:
    """A depth picked under one pixel, or one line saying why there is none (`what_to_do`: the
    caller's advice, e.g. Blender's to click elsewhere)."""
    if not np.isfinite(value) or value <= 0:
        raise NeulfError(f"the light field has no depth at pixel ({x:g}, {y:g}){where}: the ray misses the light slab, "
                         f"or what it meets lies behind the camera{what_to_do}.")
    return value


class MemberMean(torch.nn.Module):
    """The members' fields as one: the mean of their colours, and of their depth outputs
    (which are linear in disparity, slab.depth_from_unit), so every renderer path -- pixel
    samples, refocus, depth picking, fitting a held-out pose -- sees one field."""

    def __init__(self, fields: list[torch.nn.Module]):
        super().__init__()
        self.members = torch.nn.ModuleList(fields)
        self.field_name, self.field_config = fields[0].field_name, fields[0].field_config

    def forward(self, uvst: torch.Tensor):
        rgb, depth = self.members[0](uvst)
        for member in self.members[1:]:
            more_rgb, more_depth = member(uvst)
            rgb, depth = rgb + more_rgb, depth + more_depth
        return rgb / len(self.members), depth / len(self.members)

    def depth_unit(self, uvst: torch.Tensor) -> torch.Tensor:
        """forward's depth alone (the members' depth units summed in the same order)."""
        depth = field_depth_unit(self.members[0], uvst)
        for member in self.members[1:]:
            depth = depth + field_depth_unit(member, uvst)
        return depth / len(self.members)


def _field_and_slab(payload: dict, model_dir) -> tuple[torch.nn.Module, Slab]:
    """The field module and slab a loaded checkpoint describes."""
    try:
        module = build_field(payload["field"], make_config(payload["field"], payload["field_config"]))
        module.load_state_dict(payload["state_dict"])
        return module, Slab.from_dict(payload["slab"])
    except (KeyError, RuntimeError, TypeError, ValueError) as exc:
        raise NeulfError(f"the checkpoint in {model_dir} is damaged or incomplete ({type(exc).__name__}: {exc}); train again.") from None


def contrast_threshold(value) -> float:
    """`sample_contrast` checked: a colour difference from 0 (every pixel takes the points) to 1."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool) or not 0.0 <= value <= 1.0:
        raise NeulfError(f"the sample contrast is a colour difference from 0 (points in every pixel) to 1, not {value!r}.")
    return float(value)


def contrasted_pixels(colour: torch.Tensor, threshold: float) -> torch.Tensor:
    """(H, W) True where a pixel of `colour` (H, W, 3) differs from its left, right, upper or lower
    neighbour by more than `threshold` in some channel."""
    across = (colour[:, 1:] - colour[:, :-1]).abs().amax(dim=-1) > threshold
    down = (colour[1:] - colour[:-1]).abs().amax(dim=-1) > threshold
    edges = torch.zeros(colour.shape[:2], dtype=torch.bool, device=colour.device)
    edges[:, 1:] |= across
    edges[:, :-1] |= across
    edges[1:] |= down
    edges[:-1] |= down
    return edges


def pixel_offsets(samples: int, footprint: float = PIXEL_FOOTPRINT) -> np.ndarray:
    """(samples, 2) points of a pixel, in pixels from its centre: the centres of the cells of
    a square grid over the central `footprint` x `footprint` of it (1: the centre itself)."""
    if samples not in PIXEL_SAMPLES:
        raise NeulfError(f"pixel samples must be one of {', '.join(map(str, PIXEL_SAMPLES))}, not {samples}.")
    if not 0.0 <= footprint <= 1.0:
        raise NeulfError(f"the pixel footprint is a share of the pixel, from 0 to 1, not {footprint}.")
    side = math.isqrt(int(samples))
    steps = ((np.arange(side) + 0.5) / side - 0.5) * footprint
    grid_x, grid_y = np.meshgrid(steps, steps)
    return np.stack([grid_x.ravel(), grid_y.ravel()], axis=1)

