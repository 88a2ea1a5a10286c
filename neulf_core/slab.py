"""The light slab: two parallel planes that turn a ray into four numbers (u, v, s, t).

The slab frame has its origin at the mean camera centre and its z axis along the mean
viewing direction (x right and y down, like the cameras).  The uv plane is z = z_uv
(near the camera rig) and the st plane z = z_st (inside the scene).  A ray's (u, v) and
(s, t) are where its line crosses those planes; each axis is then mapped to [-1, 1] with
the training rays' range, and that normalisation is saved with the model.

Placement of the st plane: at the depth of the scene's mean disparity (the harmonic mean
of the sparse points' depths).  There the parallax of the scene around the plane averages
out, so the colour changes least with (u, v) for a fixed (s, t) and the field is smoothest
along the sparsely sampled angular axes.  See docs/BENCHMARKS.md for the measurement.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from .errors import NeulfError
from .rays import pixel_centres, view_rays
from .scene import Scene, View

# A ray must cross the planes at no more than this angle from the slab axis (cosine).
MIN_AXIS_COSINE = float(np.cos(np.radians(80.0)))
# Cameras whose view direction is further than this from the mean cannot share one slab.
MAX_VIEW_ANGLE_DEG = 65.0


# The far/near depth ratio (in slab units) above which a scene counts as deep.  Measured on
# five scenes: HCI 2.60, CanClip 1.71 and Statue 2.01 on one side, the project's synthetic
# scene 3.28 and fern 4.64 on the other (docs/DEPTH.md).
DEEP_SCENE_RATIO = 3.0


@dataclass
class Slab:
    rotation: np.ndarray   # (3, 3) rows: slab x, y, z axes in world coordinates
    origin: np.ndarray     # (3,) slab origin in world coordinates
    z_uv: float            # uv plane depth along the slab axis
    z_st: float            # st plane depth along the slab axis
    z_near: float          # scene depth range along the slab axis (for the depth output)
    z_far: float
    lo: np.ndarray         # (4,) per-axis minimum of the training (u, v, s, t)
    hi: np.ndarray         # (4,) per-axis maximum

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict:
        data = asdict(self)
        for key, value in data.items():
            if isinstance(value, np.ndarray):
                data[key] = value.tolist()
        data["uv_corners_world"] = self.plane_corners("uv").tolist()
        data["st_corners_world"] = self.plane_corners("st").tolist()
        return data

    @classmethod
    def from_dict(cls, data: dict) -> "Slab":
        arrays = {"rotation", "origin", "lo", "hi"}
        fields = cls.__dataclass_fields__
        return cls(**{k: (np.asarray(v, dtype=np.float64) if k in arrays else float(v)) for k, v in data.items() if k in fields})

    # ------------------------------------------------------------------ geometry
    def to_slab(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) - self.origin) @ self.rotation.T

    def to_world(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, dtype=np.float64) @ self.rotation + self.origin

    def origin_relative_t(self, R, t) -> np.ndarray:
        """A camera's t (world to camera) for the world moved to the slab's origin, in float64:
        rays made from it stay exact in float32 however far the model sits from its world's
        origin (render.LightField, classic.ClassicLightField)."""
        return np.asarray(t, np.float64).reshape(3) + np.asarray(R, np.float64) @ self.origin

    def plane_corners(self, plane: str) -> np.ndarray:
        """(4, 3) world corners of the uv or st plane's extent (the training rays' range)."""
        a, z = (0, self.z_uv) if plane == "uv" else (2, self.z_st)
        (x0, y0), (x1, y1) = self.lo[a:a + 2], self.hi[a:a + 2]
        corners = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])
        return self.to_world(corners)

    def __getstate__(self) -> dict:
        """Pickled and copied without the tensors `_tensors` keeps (GPU memory among them)."""
        return {k: v for k, v in self.__dict__.items() if k != "_tensor_cache"}

    def _tensors(self, device, dtype):
        """The slab's rotation, origin, centre and half-extent as tensors on `device`.

        Kept per device, dtype and values: on a GPU each copy from host memory waits for the
        GPU's queue to drain, and a training step asks for these several times."""
        # (Tensors made under inference mode cannot be saved for a backward pass: kept apart.)
        key = (str(device), dtype, torch.is_inference_mode_enabled(),
               *(np.asarray(a, dtype=np.float64).tobytes() for a in (self.rotation, self.origin, self.lo, self.hi)))
        cache = self.__dict__.setdefault("_tensor_cache", {})
        if key not in cache:
            as_t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), device=device, dtype=dtype)  # noqa: E731
            if len(cache) >= 8:  # the slab's values were changed: the old entries are not asked for again
                cache.clear()
            cache[key] = (as_t(self.rotation), as_t(self.origin), as_t((self.lo + self.hi) / 2), as_t((self.hi - self.lo) / 2))
        return cache[key]

    def rays_to_uvst(self, origins: torch.Tensor, directions: torch.Tensor, normalise: bool = True):
        """World rays -> (N, 4) (u, v, s, t) and (N,) bool: the ray crosses the planes forwards.

        Differentiable in origins and directions.  `origins` may be (3,) or (N, 3).
        """
        rotation, origin, _, _ = self._tensors(directions.device, directions.dtype)
        o = (origins - origin) @ rotation.T
        d = directions @ rotation.T
        if o.dim() == 1:
            o = o.expand_as(d)
        return self.slab_rays_to_uvst(o, d, normalise)

    def slab_rays_to_uvst(self, o: torch.Tensor, d: torch.Tensor, normalise: bool = True):
        """rays_to_uvst for rays already in the slab frame: (N, 3) points and directions."""
        _, _, centre, half = self._tensors(d.device, d.dtype)
        dz = d[:, 2]
        valid = dz > MIN_AXIS_COSINE * d.norm(dim=1)
        dz_safe = torch.where(valid, dz, torch.ones_like(dz))
        uv = o[:, :2] + d[:, :2] * ((self.z_uv - o[:, 2]) / dz_safe)[:, None]
        st = o[:, :2] + d[:, :2] * ((self.z_st - o[:, 2]) / dz_safe)[:, None]
        uvst = torch.cat([uv, st], dim=1)
        if normalise:
            uvst = (uvst - centre) / half
        return uvst, valid

    def plane_crossings(self, uvst: torch.Tensor, normalised: bool = True):
        """(N, 4) -> the rays' points on the uv and on the st plane, (N, 3) each, slab frame."""
        _, _, centre, half = self._tensors(uvst.device, uvst.dtype)
        if normalised:
            uvst = uvst * half + centre
        n = uvst.shape[0]
        p_uv = torch.cat([uvst[:, :2], torch.full((n, 1), self.z_uv, device=uvst.device, dtype=uvst.dtype)], 1)
        p_st = torch.cat([uvst[:, 2:], torch.full((n, 1), self.z_st, device=uvst.device, dtype=uvst.dtype)], 1)
        return p_uv, p_st

    def uvst_to_rays(self, uvst: torch.Tensor, normalised: bool = True):
        """(N, 4) -> world points on the uv plane (N, 3) and unit directions towards st (N, 3)."""
        rotation, origin, _, _ = self._tensors(uvst.device, uvst.dtype)
        p_uv, p_st = self.plane_crossings(uvst, normalised)
        d = p_st - p_uv
        d = d / d.norm(dim=1, keepdim=True)
        return p_uv @ rotation + origin, d @ rotation

    def depth_from_unit(self, unit: torch.Tensor) -> torch.Tensor:
        """Map the field's [0, 1] depth output to slab-axis depth, linear in disparity
        (1 -> near, 0 -> far) so near objects get the finer resolution."""
        inv_near, inv_far = 1.0 / self.z_near, 1.0 / self.z_far
        return 1.0 / (inv_far + unit * (inv_near - inv_far))

    def unit_from_depth(self, depth: torch.Tensor) -> torch.Tensor:
        inv_near, inv_far = 1.0 / self.z_near, 1.0 / self.z_far
        return (1.0 / depth - inv_far) / (inv_near - inv_far)

    @property
    def is_deep(self) -> bool:
        """A scene deep for its slab: far/near above DEEP_SCENE_RATIO.  The fast field's
        training adapts to it (depth layers, the teacher's pull: train.py, teacher.py)."""
        return self.z_far / self.z_near > DEEP_SCENE_RATIO


# ----------------------------------------------------------------------------- fitting


def slab_frame(views: list[View]) -> tuple[np.ndarray, np.ndarray]:
    """(rotation, origin) from the mean camera orientation and centre; raises when the
    cameras do not look one way (a 360-degree or inward-facing ring)."""
    forwards = np.stack([v.forward for v in views])
    rights = np.stack([v.R[0] for v in views])
    mean_forward = forwards.mean(axis=0)
    spread = np.linalg.norm(mean_forward)
    z = mean_forward / max(spread, 1e-12)
    angles = np.degrees(np.arccos(np.clip(forwards @ z, -1, 1)))
    worst = int(np.argmax(angles))
    if spread < 0.5 or angles[worst] > MAX_VIEW_ANGLE_DEG:
        raise NeulfError(
            f"the capture is not forward-facing: camera {views[worst].name} looks {angles[worst]:.0f} degrees away "
            f"from the mean view direction (limit {MAX_VIEW_ANGLE_DEG:.0f}). A two-plane light field needs all cameras "
            "on one side of the scene looking the same way; a 360-degree or surround capture cannot share one light slab. "
            f"Where only a few photos look elsewhere, hold them out of training with --exclude {views[worst].name},... "
            "(--exclude names every view held out)."
        )
    x = rights.mean(axis=0)
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    origin = np.mean([v.center for v in views], axis=0)
    return np.stack([x, y, z]), origin


# Sparse points nearer the cameras than this share of the median depth, a minority of them
# (STRAY_MOST), are strays: 10 % of the points 1-5 cm from the lens (0.003-0.017 of the median)
# had put the st plane at 0.38 of a scene at 3, and the held-out views scored 10.7 dB instead of
# 43.7.  Real near content lies farther out: the reference captures' and the project's scenes'
# nearest kept point at 0.40-0.87 of the median, a card at 0.23 of it in a reader's test scene
# (which a share of 0.25 had cut away: 18.9 -> 15.1 dB).
STRAY_DEPTH_SHARE = 0.05
STRAY_MOST = 0.2


def scene_depths(scene: Scene, rotation: np.ndarray, origin: np.ndarray, drop_strays: bool = True) -> np.ndarray:
    """Depths of the scene's content along the slab axis (from sparse points or LLFF bounds);
    `drop_strays`: without the points nearer than STRAY_DEPTH_SHARE of the median (a note)."""
    if len(scene.points) >= 8:
        z = (scene.points - origin) @ rotation[2]
        z = z[z > 0]
        if len(z) >= 8:
            lo, hi = np.percentile(z, [1, 99])
            z = z[(z >= lo) & (z <= hi)]
            stray = z < STRAY_DEPTH_SHARE * np.median(z)
            if drop_strays and stray.any() and stray.mean() <= STRAY_MOST:
                note = (f"{int(stray.sum())} of the model's {len(z)} points lie nearer the cameras than a twentieth "
                        "of the scene's median depth (stray points): the light slab is placed without them (--near "
                        "and --st-depth place it by hand)")
                if note not in scene.notes:
                    scene.notes.append(note)
                z = z[~stray]
            return z
    if scene.depth_bounds is not None and np.isfinite(scene.depth_bounds).any():
        # (NaN: a row whose near/far were not usable, scene._read_poses_bounds)
        return np.array([np.nanmin(scene.depth_bounds[:, 0]), np.nanmax(scene.depth_bounds[:, 1])])
    if scene.kind == "llff":
        raise NeulfError(
            "poses_bounds.npy holds no usable near/far depths (15 numbers a row, not 17, or none finite with "
            "0 < near < far), so the scene's depth is unknown; give the depth of the st plane and the depth range "
            "with --st-depth, --near, --far."
        )
    raise NeulfError(
        "the model has no usable 3D points in front of the cameras, so the scene's depth is unknown; "
        "rerun reconstruct, or give the depth of the st plane and the depth range with --st-depth, --near, --far."
    )


def fit_slab(scene: Scene, train_views: list[View], *, scale: float = 1.0, st_depth: float | None = None,
             uv_depth: float = 0.0, near: float | None = None, far: float | None = None) -> Slab:
    """Place the slab for `train_views` and fit the (u, v, s, t) normalisation to their rays."""
    rotation, origin = slab_frame(train_views)
    asked = near is not None and far is not None
    if st_depth is None or near is None or far is None:
        depths = scene_depths(scene, rotation, origin, drop_strays=near is None)  # (--near: the user's framing)
        near = float(near if near is not None else depths.min())
        far = float(far if far is not None else depths.max())
        # (within the range asked for: a point outside it is not what the user framed)
        inside = depths[(depths >= near) & (depths <= far)]
        st_depth = float(st_depth if st_depth is not None else
                         1.0 / np.mean(1.0 / inside) if len(inside) else 2.0 / (1.0 / near + 1.0 / far))
    if asked and not (0 < near < far):
        raise NeulfError(f"depth range --near {near:g} --far {far:g} is not valid: need 0 < near < far.")
    if not (0 < near <= far):  # (the points' own: all at one depth, a flat subject, is fine: the margins give range)
        raise NeulfError(f"the scene's depth range from its points ({near:g} to {far:g}) is not valid; give it with "
                         "--near and --far (and the st plane with --st-depth).")
    if st_depth <= uv_depth:
        raise NeulfError(f"the st plane (depth {st_depth}) must lie beyond the uv plane (depth {uv_depth}).")
    slab = Slab(rotation, origin, float(uv_depth), float(st_depth), 0.9 * near, 1.1 * far, np.zeros(4), np.ones(4))
    lo, hi = _uvst_range(slab, train_views, scale)
    slab.lo, slab.hi = lo, hi
    return slab


def _border_pixels(width: int, height: int) -> np.ndarray:
    """The outermost pixel centres: a view's (u, v, s, t) extremes lie on its border."""
    pixels = pixel_centres(width, height).reshape(height, width, 2)
    return np.concatenate([pixels[0], pixels[-1], pixels[:, 0], pixels[:, -1]])


def wide_views(slab: Slab, views: list[View], scale: float, factor: float = 2.0) -> list[tuple[str, float]]:
    """(name, ratio) of the views whose extent on the st plane is more than `factor` times the
    median view's along s or t: a wider lens or a fisheye among the photos.  The slab's range
    spans every view's, and the texture's size follows the photos' pixels, so one such photo
    leaves the others a smaller share of the detail (one 94-degree photo among 56-degree ones:
    the held-out views 31.3 -> 27.5 dB; a fisheye 20.6)."""
    if len(views) < 3:
        return []
    spans = []
    for view in views:
        camera = view.scaled_camera(scale)
        origin, dirs = view_rays(camera, view.R, view.t, _border_pixels(int(camera.width), int(camera.height)))
        uvst, valid = slab.rays_to_uvst(torch.from_numpy(origin), torch.from_numpy(dirs), normalise=False)
        st = uvst[valid][:, 2:].numpy()
        spans.append(st.max(0) - st.min(0) if len(st) else np.zeros(2))
    spans = np.array(spans)
    ratio = (spans / np.maximum(np.median(spans, axis=0), 1e-12)).max(axis=1)
    return [(view.name, float(r)) for view, r in zip(views, ratio) if r > factor]


def _uvst_range(slab: Slab, views: list[View], scale: float) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.full(4, np.inf), np.full(4, -np.inf)
    for view in views:
        camera = view.scaled_camera(scale)
        origin, dirs = view_rays(camera, view.R, view.t, _border_pixels(int(camera.width), int(camera.height)))
        uvst, valid = slab.rays_to_uvst(torch.from_numpy(origin), torch.from_numpy(dirs), normalise=False)
        if not bool(valid.all()):
            raise NeulfError(
                f"some rays of view {view.name} run almost parallel to the light slab (more than 80 degrees off its "
                "axis): the field of view is too wide or the camera turned too far for a two-plane light field."
            )
        lo = np.minimum(lo, uvst.min(0).values.numpy())
        hi = np.maximum(hi, uvst.max(0).values.numpy())
    # Guard against a degenerate axis (all cameras on a line): give it a small width.
    width = np.maximum(hi - lo, 1e-6 * max(1.0, float(np.abs(hi - lo).max())))
    return (lo + hi) / 2 - width / 2, (lo + hi) / 2 + width / 2
