"""A grid radiance field rendered by volume rendering: the paper's point of comparison.

NeuLF's claim is that a light field handles view-dependent effects (mirror reflections,
refraction) better than volume rendering, which must explain each pixel as colour emitted
by points along the ray, so that a reflection has to be faked by geometry behind the mirror
or by colour that changes with the viewing direction.  This module is the volume renderer
that measures the claim (benchmarks/view_dependence.py, issue 4); it is a baseline, not part
of the product, and nothing in neulf_core imports it.

The model follows the fast explicit-grid radiance fields (DVGO, Plenoxels), the volume
renderers that train in minutes rather than a day, so the comparison is of the two ways of
representing a scene, not of a fast method against a slow one:
- a density grid and a feature grid over the rig's frustum: a point at (x, y, z) in the slab
  frame (origin the mean camera, z its mean view direction; neulf_core.slab) sits at
  (x / z, y / z, 1 / z), each mapped to [-1, 1] over the training rays' range, as NeRF's NDC
  maps a forward-facing scene;
- 48 samples a ray, evenly spaced in disparity between the scene's near and far depths
  (jittered within their bins in training), alpha-composited front to back;
- a sample's colour from a small MLP of its features and the ray's direction (positional
  encoding), so colour may change with the viewpoint, as DVGO's does;
- total variation on both grids (the views are few: forward-facing grid methods all need it),
  and the grids trained coarse to fine (half their resolution for the first third).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from neulf_core.rays import view_rays
from neulf_core.scene import View


@dataclass
class VolumeConfig:
    # 96x72x48 cells, 48 samples and 2048 rays a step: 0.35 s a step on 2 CPU threads, where
    # 128x96x64, 64 and 4096 took 1.3 s (the synthetic scene at 160x120)
    resolution: tuple[int, int, int] = (96, 72, 48)  # cells along x / z, y / z and disparity
    features: int = 12
    samples: int = 48                 # per ray, evenly spaced in disparity
    hidden: int = 64
    direction_frequencies: int = 4    # the view direction's positional encoding
    batch: int = 2048                 # rays per step
    steps: int = 2400                 # 1200 was short of it: the Lambertian scene 31.06 -> 33.08 dB at 2400
    grid_lr: float = 0.1              # Adam on the grids (DVGO's rate)
    mlp_lr: float = 1e-3
    lr_final_ratio: float = 0.1       # exponential decay to this share of the rates
    tv_density: float = 1e-3          # total variation weights (mean squared neighbour difference)
    tv_features: float = 1e-4
    coarse_share: float = 1 / 3       # the grids at half resolution for this share of the steps
    colour_threshold: float = 1e-4    # samples under this compositing weight skip the colour MLP
    density_shift: float = -4.6       # softplus(0 + shift) ~ 0.01: each sample ~1 % opaque at the start


class FrustumGrid:
    """Maps slab-frame points to grid coordinates in [-1, 1]^3 (x / z, y / z, disparity)."""

    def __init__(self, centre_xy: torch.Tensor, half_xy: torch.Tensor, near: float, far: float):
        self.centre_xy, self.half_xy = centre_xy, half_xy
        self.near, self.far = near, far

    @classmethod
    def fit(cls, origins: torch.Tensor, directions: torch.Tensor, near: float, far: float, margin: float = 0.02):
        """The grid that holds every training ray between the near and far depths."""
        extents = []
        for depth in (near, far):
            points = _points_at_depths(origins, directions, torch.full((len(origins), 1), depth))[:, 0]
            extents.append(points[:, :2] / points[:, 2:])
        extents = torch.cat(extents)
        lo, hi = extents.min(0).values, extents.max(0).values
        return cls((lo + hi) / 2, (hi - lo) / 2 * (1 + margin), near, far)

    def coordinates(self, points: torch.Tensor) -> torch.Tensor:
        xy = (points[..., :2] / points[..., 2:] - self.centre_xy) / self.half_xy
        disparity = 1.0 / points[..., 2:]
        d = 2 * (disparity - 1 / self.far) / (1 / self.near - 1 / self.far) - 1
        return torch.cat([xy, d], -1)

    def sample_depths(self, rays: int, samples: int, jitter: torch.Generator | None) -> torch.Tensor:
        """(rays, samples) depths, evenly spaced in disparity (far to near bins read front to back)."""
        offsets = torch.rand(rays, samples, generator=jitter) if jitter is not None else torch.full((rays, samples), 0.5)
        bins = (torch.arange(samples, dtype=torch.float32) + offsets) / samples  # 0 near ... 1 far
        disparity = 1 / self.near + bins * (1 / self.far - 1 / self.near)
        return 1 / disparity


def _points_at_depths(origins: torch.Tensor, directions: torch.Tensor, depths: torch.Tensor) -> torch.Tensor:
    """(R, S, 3) the points of each ray at slab depths z (R, S)."""
    along = (depths - origins[:, 2:]) / directions[:, 2:]
    return origins[:, None, :] + along[..., None] * directions[:, None, :]


def _encode_directions(directions: torch.Tensor, frequencies: int) -> torch.Tensor:
    bands = [directions]
    for k in range(frequencies):
        bands += [torch.sin((2.0 ** k) * math.pi * directions), torch.cos((2.0 ** k) * math.pi * directions)]
    return torch.cat(bands, -1)


def _total_variation(grid: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of neighbouring cells along each of the grid's three axes."""
    return sum(((grid.narrow(axis, 1, grid.shape[axis] - 1) - grid.narrow(axis, 0, grid.shape[axis] - 1)) ** 2).mean()
               for axis in (2, 3, 4))


class VolumeField(nn.Module):
    def __init__(self, config: VolumeConfig, frustum: FrustumGrid, resolution: tuple[int, int, int]):
        super().__init__()
        self.config, self.frustum = config, frustum
        nx, ny, nd = resolution
        self.density = nn.Parameter(torch.zeros(1, 1, nd, ny, nx))
        self.features = nn.Parameter(torch.zeros(1, config.features, nd, ny, nx))
        encoded = 3 * (1 + 2 * config.direction_frequencies)
        self.colour = nn.Sequential(nn.Linear(config.features + encoded, config.hidden), nn.ReLU(),
                                    nn.Linear(config.hidden, config.hidden), nn.ReLU(), nn.Linear(config.hidden, 3))

    def upsample(self, resolution: tuple[int, int, int]) -> None:
        """The grids at a finer resolution, trilinearly interpolated from the coarse ones."""
        nx, ny, nd = resolution
        with torch.no_grad():
            self.density = nn.Parameter(F.interpolate(self.density, size=(nd, ny, nx), mode="trilinear", align_corners=True))
            self.features = nn.Parameter(F.interpolate(self.features, size=(nd, ny, nx), mode="trilinear", align_corners=True))

    def _read(self, grid: torch.Tensor, coordinates: torch.Tensor) -> torch.Tensor:
        """(M, C) grid values at (M, 3) coordinates."""
        values = F.grid_sample(grid, coordinates.view(1, 1, 1, -1, 3), mode="bilinear", align_corners=True)
        return values.view(grid.shape[1], -1).t()

    def forward(self, origins: torch.Tensor, directions: torch.Tensor, jitter: torch.Generator | None = None):
        """(R, 3) colours of the rays (and their (R,) opacity)."""
        config = self.config
        depths = self.frustum.sample_depths(len(origins), config.samples, jitter)
        coordinates = self.frustum.coordinates(_points_at_depths(origins, directions, depths))
        raw = self._read(self.density, coordinates.reshape(-1, 3)).view(len(origins), config.samples)
        alpha = 1 - torch.exp(-F.softplus(raw + config.density_shift))
        transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1] + 1e-10], 1), 1)
        weights = alpha * transmittance
        keep = weights.detach() > config.colour_threshold
        ray_of_sample = torch.arange(len(origins)).unsqueeze(1).expand_as(keep)[keep]
        features = self._read(self.features, coordinates[keep])
        encoded = _encode_directions(directions, config.direction_frequencies)[ray_of_sample]
        colour = torch.sigmoid(self.colour(torch.cat([features, encoded], -1)))
        rgb = torch.zeros(len(origins), 3).index_add_(0, ray_of_sample, weights[keep][:, None] * colour)
        return rgb, weights.sum(1)

    def regulariser(self) -> torch.Tensor:
        return (self.config.tv_density * _total_variation(self.density)
                + self.config.tv_features * _total_variation(self.features))


def slab_rays(views: list[View], scale: float, rotation: np.ndarray, origin: np.ndarray, with_colours: bool = True):
    """Every pixel's ray of `views` in the slab frame: (origins, directions, colours or None), float32."""
    origins, directions, colours = [], [], []
    for view in views:
        camera = view.scaled_camera(scale)
        centre, bearing = view_rays(camera, view.R, view.t)
        directions.append(bearing @ rotation.T)
        origins.append(np.broadcast_to(rotation @ (centre - origin), bearing.shape))
        if with_colours:
            colours.append(view.load_image(scale).reshape(-1, 3).astype(np.float32) / 255.0)
    as_tensor = lambda parts: torch.from_numpy(np.concatenate(parts).astype(np.float32))  # noqa: E731
    return as_tensor(origins), as_tensor(directions), as_tensor(colours) if with_colours else None


class VolumeModel:
    """A trained VolumeField with the slab frame it lives in; renders views."""

    def __init__(self, field: VolumeField, rotation: np.ndarray, origin: np.ndarray):
        self.field, self.rotation, self.origin = field, rotation, origin

    @torch.no_grad()
    def render_view(self, view: View, scale: float, chunk: int = 8192) -> np.ndarray:
        origins, directions, _ = slab_rays([view], scale, self.rotation, self.origin, with_colours=False)
        rgb = torch.cat([self.field(origins[i:i + chunk], directions[i:i + chunk])[0] for i in range(0, len(origins), chunk)])
        width, height = view.scaled_camera(scale).width, view.scaled_camera(scale).height
        return rgb.view(int(height), int(width), 3).clamp(0, 1).numpy()


def train_volume(train_views: list[View], scale: float, rotation: np.ndarray, origin: np.ndarray, near: float,
                 far: float, config: VolumeConfig = VolumeConfig(), seed: int = 0, progress=None) -> tuple[VolumeModel, dict]:
    """Train the baseline on `train_views` (photos at `scale`) in the slab frame (rotation,
    origin) between the depths `near` and `far`.  Returns the model and a record (steps,
    seconds, final training loss)."""
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    origins, directions, colours = slab_rays(train_views, scale, rotation, origin)
    frustum = FrustumGrid.fit(origins, directions, near, far)
    full = tuple(config.resolution)
    coarse = tuple(max(2, n // 2) for n in full)
    coarse_steps = int(config.coarse_share * config.steps)
    field = VolumeField(config, frustum, coarse if coarse_steps > 0 else full)

    grid_optimiser = torch.optim.Adam([field.density, field.features], lr=config.grid_lr)
    mlp_optimiser = torch.optim.Adam(field.colour.parameters(), lr=config.mlp_lr)
    started, loss_value = time.monotonic(), float("nan")
    for step in range(config.steps):
        if step == coarse_steps and coarse_steps > 0:
            field.upsample(full)
            grid_optimiser = torch.optim.Adam([field.density, field.features], lr=config.grid_lr)
        decay = config.lr_final_ratio ** (step / config.steps)
        for group in grid_optimiser.param_groups:
            group["lr"] = config.grid_lr * decay
        for group in mlp_optimiser.param_groups:
            group["lr"] = config.mlp_lr * decay
        pick = torch.randint(len(origins), (config.batch,), generator=generator)
        rgb, _ = field(origins[pick], directions[pick], jitter=generator)
        loss = ((rgb - colours[pick]) ** 2).mean()
        objective = loss + field.regulariser()
        grid_optimiser.zero_grad(set_to_none=True)
        mlp_optimiser.zero_grad(set_to_none=True)
        objective.backward()
        grid_optimiser.step()
        mlp_optimiser.step()
        loss_value = float(loss.detach())
        if progress is not None and (step + 1) % 250 == 0:
            progress(step + 1, loss_value, time.monotonic() - started)
    record = {"steps": config.steps, "seconds": time.monotonic() - started, "final_loss": loss_value,
              "grid_cells": int(np.prod(full)), "parameters": sum(p.numel() for p in field.parameters())}
    return VolumeModel(field, rotation, origin), record
