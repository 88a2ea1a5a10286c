"""Classic light field rendering straight from the training photos (no training).

The paper's "baseline" and the floor every learned method must clear; also an instant
preview while a network trains.  Two modes (Levoy & Hanrahan 1996; Isaksen et al. 2000):

- `plane`: every output ray meets one focal plane (the slab's st plane); that point is
  projected into the `k` training photos nearest the output camera and their colours are
  blended with inverse-square distance weights.
- `sweep`: a per-pixel plane sweep: for `depths` planes between the scene's near and far
  (uniform in disparity), the same projection and blend; each pixel keeps the depth where
  the photos agree best (lowest weighted colour variance, smoothed over a small window).

Photos are undistorted to pinhole images once at load (through pycolmap's own camera
model), so the renderer only projects with K.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .rays import pinhole_rays, view_rays
from .scene import View
from .slab import Slab


def undistort_to_pinhole(view: View, scale: float, photo: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The view's photo (`photo`, read at `scale` already, or read here) resampled to the
    pinhole camera with the same K: (image, K)."""
    camera = view.scaled_camera(scale)
    photo = view.load_image(scale) if photo is None else photo
    K = np.asarray(camera.calibration_matrix(), dtype=np.float64)
    if camera.model_name in ("PINHOLE", "SIMPLE_PINHOLE"):
        return photo, K
    width, height = int(camera.width), int(camera.height)
    xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    normalised = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1]], -1).reshape(-1, 2)
    distorted = np.asarray(camera.img_from_cam(np.concatenate([normalised, np.ones((len(normalised), 1))], 1)))
    grid = torch.from_numpy(distorted.reshape(1, height, width, 2)).float()
    grid[..., 0] = grid[..., 0] / width * 2 - 1
    grid[..., 1] = grid[..., 1] / height * 2 - 1
    image = torch.from_numpy(np.array(photo)).permute(2, 0, 1)[None].float()
    resampled = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return resampled[0].permute(1, 2, 0).round().clamp(0, 255).byte().numpy(), K


def common_size(images, Ks) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The pinhole photos (H, W, 3) and their K, all resampled to one size, so they stack into
    one tensor: a scene's photo files may differ in size (a resized copy among them; scene.py
    scales each view's intrinsics to its file).  The common size is the most frequent one (on
    a tie the largest); a photo of another size is resized bilinearly to it and its K scaled
    with it, x and y apart (pixel centres at +0.5: the edges map onto the edges)."""
    sizes = [np.asarray(image).shape[:2] for image in images]
    if len(set(sizes)) <= 1:
        return list(images), list(Ks)
    counts: dict = {}
    for size in sizes:
        counts[size] = counts.get(size, 0) + 1
    height, width = max(counts, key=lambda size: (counts[size], size[0] * size[1]))
    out_images, out_Ks = [], []
    for image, K, (h, w) in zip(images, Ks, sizes):
        if (h, w) != (height, width):
            tensor = torch.from_numpy(np.array(image)).permute(2, 0, 1)[None].float()
            tensor = F.interpolate(tensor, size=(height, width), mode="bilinear", align_corners=False,
                                   antialias=h > height or w > width)
            image = tensor[0].permute(1, 2, 0).round().clamp(0, 255).byte().numpy()
            K = np.diag([width / w, height / h, 1.0]) @ np.asarray(K, dtype=np.float64)
        out_images.append(image)
        out_Ks.append(K)
    return out_images, out_Ks


@dataclass
class SweepDepth:
    """The plane sweep's per-pixel depth, (H * W,) tensors: `unit` in [0, 1]
    (Slab.depth_from_unit), the photo-consistency cost there, the mean cost over the depths
    that two or more photos see (a flat region matches everywhere: mean close to best), and
    how many photos see the point at the chosen depth."""

    unit: torch.Tensor
    cost: torch.Tensor
    mean_cost: torch.Tensor
    seen: torch.Tensor


UNSEEN_COST = 1e3  # far above any colour variance (colours are in [0, 1])


class ClassicLightField:
    def __init__(self, views: list[View], slab: Slab, scale: float, device="cpu", photos: list | None = None):
        """`photos`: the views' photos at `scale` where the caller has read them (else read here)."""
        self.slab = slab
        self.device = torch.device(device)
        images, Ks = zip(*(undistort_to_pinhole(v, scale, photo)
                           for v, photo in zip(views, photos if photos is not None else [None] * len(views))))
        images, Ks = common_size(images, Ks)
        self.images = torch.stack([torch.from_numpy(np.array(i)).permute(2, 0, 1) for i in images]).to(self.device)  # (V, 3, H, W) uint8
        self.K = torch.as_tensor(np.stack(Ks), device=self.device, dtype=torch.float32)
        # The photos' cameras in a world moved to the slab's origin, in float64 before float32: a
        # COLMAP model can sit 1e5-1e7 units from its origin, where float32 world coordinates are
        # coarser than the rig (the sweep's targets at 1e7 off: a mean error of 0.15 of the depth
        # range; render.LightField does the same).
        self.R = torch.as_tensor(np.stack([v.R for v in views]), device=self.device, dtype=torch.float32)
        self.t = torch.as_tensor(np.stack([self.slab.origin_relative_t(v.R, v.t) for v in views]), device=self.device,
                                 dtype=torch.float32)
        self.centres = torch.as_tensor(np.stack([v.center - slab.origin for v in views]), device=self.device,
                                       dtype=torch.float32)

    def _nearest(self, centre: torch.Tensor, k: int, exclude: int | None = None):
        distance = (self.centres - centre).norm(dim=1)
        if exclude is not None:  # a training view rendered from the others (the depth teacher)
            distance = distance.clone()
            distance[exclude] = float("inf")
        order = torch.argsort(distance)[:k]
        weights = 1.0 / (distance[order] ** 2 + 1e-8)
        return order, weights / weights.sum()

    def _projection(self, index: torch.Tensor, origin: torch.Tensor, directions: torch.Tensor):
        """(base (k, 1, 3), step (k, N, 3)): where the point at distance s along ray n falls in
        photo k, as homogeneous grid_sample coordinates base + s * step (x / z, y / z in
        [-1, 1] inside the photo; z the depth in that camera).  A sweep's points all lie on
        its output rays, so the photos' projection of every plane is this one line each:
        computed once per render instead of once per plane, the sweep teacher takes half the
        time (CanClip's 26 views at 240x135, one thread: 7.59 -> 3.96 s; docs/BENCHMARKS.md,
        "The sweep's projection")."""
        height, width = self.images.shape[2:]
        to_grid = torch.tensor([[2.0 / width, 0.0, -1.0], [0.0, 2.0 / height, -1.0], [0.0, 0.0, 1.0]],
                               device=self.device)
        project = to_grid @ self.K[index]  # (k, 3, 3): camera frame -> homogeneous grid coordinates
        base = torch.einsum("kij,kj->ki", project, torch.einsum("kij,j->ki", self.R[index], origin) + self.t[index])
        step = torch.einsum("kij,nj->kni", project @ self.R[index], directions)
        return base[:, None], step

    @staticmethod
    def _sample(base: torch.Tensor, step: torch.Tensor, distance: torch.Tensor, photos: torch.Tensor):
        """Colours (k, 3, N) and visibility (k, N) of the points at `distance` (N,) along the
        output rays, in `photos` (those photos as floats in [0, 1], converted once per render,
        not per depth).  Channels first, as grid_sample writes them: the sweep's arithmetic
        then runs along the N contiguous pixels (with (k, N, 3) views the whole sweep took a
        third longer)."""
        point = torch.addcmul(base, step, distance[None, :, None])  # (k, N, 3)
        z = point[..., 2:]
        grid = point[..., :2] / z.clamp_min(1e-6)
        colours = F.grid_sample(photos, grid[:, :, None], mode="bilinear", padding_mode="border", align_corners=False)
        inside = (grid.abs().amax(-1) <= 1) & (z[..., 0] > 0)
        return colours[..., 0], inside

    def render(self, K, width: int, height: int, R, t, **options) -> np.ndarray:
        """(H, W, 3) float image of a pinhole camera (world-to-camera R, t)."""
        origin, directions = pinhole_rays(K, R, self.slab.origin_relative_t(R, t), width, height, self.device, torch.float32)
        return self.render_rays(origin, directions, width, height, **options)

    def render_view(self, view: View, scale: float, **options) -> np.ndarray:
        """A registered view through its own camera model, aligned with its photo."""
        camera = view.scaled_camera(scale)
        origin, directions = view_rays(camera, view.R, self.slab.origin_relative_t(view.R, view.t))
        as_t = lambda a: torch.as_tensor(a, device=self.device, dtype=torch.float32)  # noqa: E731
        return self.render_rays(as_t(origin), as_t(directions), int(camera.width), int(camera.height), **options)

    @torch.no_grad()
    def render_rays(self, origin: torch.Tensor, directions: torch.Tensor, width: int, height: int, *,
                    mode: str = "sweep", depths: int = 32, k: int = 4, window: int = 5, exclude: int | None = None,
                    with_depth: bool = False):
        """The (H, W, 3) image; with_depth: also the sweep's per-pixel depth (SweepDepth).  `origin`
        is relative to the slab's origin (`Slab.origin_relative_t`)."""
        available = len(self.centres) - (exclude is not None)
        index, weights = self._nearest(origin, min(k, available), exclude)
        rotation = torch.as_tensor(self.slab.rotation, device=self.device, dtype=torch.float32)
        o_z = float(origin @ rotation[2])
        d_z = directions @ rotation[2]
        if mode == "plane":
            plane_depths = torch.tensor([self.slab.z_st], device=self.device)
        else:
            unit = torch.linspace(0, 1, depths, device=self.device)
            plane_depths = self.slab.depth_from_unit(unit).float()
        best_cost = torch.full((height * width,), float("inf"), device=self.device)
        best_colour = torch.zeros(3, height * width, device=self.device)
        best_unit = torch.zeros(height * width, device=self.device)
        best_seen = torch.zeros(height * width, device=self.device)
        cost_sum = torch.zeros(height * width, device=self.device)
        cost_count = torch.zeros(height * width, device=self.device)
        photos = self.images[index].float() / 255.0
        base, step = self._projection(index, origin, directions)
        for i, z in enumerate(plane_depths):
            colours, inside = self._sample(base, step, (z - o_z) / d_z, photos)
            w = weights[:, None] * inside.float() + 1e-6
            w = (w / w.sum(0, keepdim=True))[:, None]  # (k, 1, N)
            mean = (w * colours).sum(0)  # (3, N)
            if mode == "plane":
                return mean.t().reshape(height, width, 3).cpu().numpy()
            variance = (w * (colours - mean) ** 2).sum(0).sum(0)
            cost = F.avg_pool2d(variance.reshape(1, 1, height, width), window, stride=1, padding=window // 2,
                                count_include_pad=False).reshape(-1)
            # One photo always agrees with itself: a depth that fewer than two photos see
            # (past the frame's edge) wins only where no depth is seen by two.
            seen = inside.float().sum(0)
            unseen = (seen < 2).float()
            cost_sum += cost * (1 - unseen)
            cost_count += 1 - unseen
            cost = cost + UNSEEN_COST * unseen
            better = cost < best_cost
            best_cost = torch.where(better, cost, best_cost)
            best_colour = torch.where(better, mean, best_colour)
            best_unit = torch.where(better, i / max(1, len(plane_depths) - 1), best_unit)
            best_seen = torch.where(better, seen, best_seen)
        image = best_colour.t().reshape(height, width, 3).cpu().numpy()
        if not with_depth:
            return image
        return image, SweepDepth(best_unit, best_cost, cost_sum / cost_count.clamp_min(1), best_seen)
