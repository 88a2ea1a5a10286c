"""The paper's multi-view consistency losses (Sec. "4D Light Field Scene Depth Estimation").

A training ray r from camera k has a predicted depth; with it the ray meets the scene at a
point P.  The rays from P back to the K nearest training cameras j are re-parameterised
through the slab -- differentiably, so the gradient reaches the predicted depth -- and the
field is asked for their colours and depths:

    L_mp = | c(r) - sum_j w_kj c(r_kj) |^2      L_d = | d(r) - sum_j w_kj d(r_kj) |^2

with w_kj the normalised inverse-square distances between the cameras k and j.  Two
choices here, both deliberate:
- c(r) is the photo's colour of r, not the network's prediction for it as in the paper:
  under the photometric loss they agree, and the photo cannot be pulled towards a blur.
- Depth is compared on the field's [0, 1] output, which is linear in inverse slab-axis
  depth.  A point's slab-axis depth is the same from every camera (all rays cross the same
  planes), so the comparison is geometrically meaningful from any neighbour.
Neighbour rays that leave the training rays' (u, v, s, t) range are dropped and the
weights renormalised: the field knows nothing there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .rows import rows_of
from .scene import camera_gaps

# Neighbour rays this far outside the normalised training range are not used.
RANGE_MARGIN = 1.05


@dataclass
class CameraNeighbours:
    centres: torch.Tensor   # (V, 3) training camera centres in slab coordinates
    index: torch.Tensor     # (V, K) the K nearest other training cameras
    weights: torch.Tensor   # (V, K) normalised inverse-square distances

    def to(self, device) -> "CameraNeighbours":
        return CameraNeighbours(self.centres.to(device), self.index.to(device), self.weights.to(device))

    def with_centres(self, centres: torch.Tensor) -> "CameraNeighbours":
        """The same neighbours standing at `centres` (V, 3) (refined poses): the neighbour
        choice and weights stay those of the cameras' first positions."""
        return CameraNeighbours(centres, self.index, self.weights)


def camera_neighbours(centres_world: np.ndarray, slab, k: int = 5) -> CameraNeighbours:
    """The K nearest training cameras of each training camera (the paper uses K = 5)."""
    centres = slab.to_slab(np.asarray(centres_world, dtype=np.float64))
    k = min(k, len(centres) - 1)
    if k < 1:
        raise ValueError("multi-view losses need at least two training views")
    distance = camera_gaps(centres)
    index = np.argsort(distance, axis=1)[:, :k]
    inverse_square = 1.0 / np.maximum(np.take_along_axis(distance, index, 1), 1e-9) ** 2
    weights = inverse_square / inverse_square.sum(1, keepdims=True)
    return CameraNeighbours(torch.tensor(centres, dtype=torch.float32), torch.tensor(index, dtype=torch.long),
                            torch.tensor(weights, dtype=torch.float32))


class SlabGeometry:
    """The slab quantities the re-parameterisation needs, as tensors on one device."""

    def __init__(self, slab, device):
        centre, half = (slab.lo + slab.hi) / 2, (slab.hi - slab.lo) / 2
        self.centre = torch.tensor(centre, dtype=torch.float32, device=device)
        self.half = torch.tensor(half, dtype=torch.float32, device=device)
        self.z_uv, self.z_st = float(slab.z_uv), float(slab.z_st)
        self.depth = slab.depth_from_unit  # the field's [0, 1] output -> slab-axis depth

    def surface_points(self, uvst: torch.Tensor, unit: torch.Tensor) -> torch.Tensor:
        """(N, 3) slab-frame points where the rays `uvst` (normalised) reach depth `unit`."""
        raw = uvst * self.half + self.centre
        uv, st = raw[:, :2], raw[:, 2:]
        z = self.depth(unit.view(-1, 1))
        along = (z - self.z_uv) / (self.z_st - self.z_uv)
        return torch.cat([uv + (st - uv) * along, z], 1)

    def rays_through(self, centres: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised (..., 4) uvst of the rays from `centres` (..., 3) to `points` (..., 3),
        and whether each crosses the planes forwards inside the training range."""
        dz = points[..., 2:] - centres[..., 2:]
        forwards = dz[..., 0] > 1e-6
        dz = torch.where(forwards[..., None], dz, torch.ones_like(dz))
        slope = (points[..., :2] - centres[..., :2]) / dz
        uv = centres[..., :2] + slope * (self.z_uv - centres[..., 2:])
        st = centres[..., :2] + slope * (self.z_st - centres[..., 2:])
        uvst = (torch.cat([uv, st], -1) - self.centre) / self.half
        inside = forwards & (uvst.abs() <= RANGE_MARGIN).all(-1)
        return uvst, inside


def multiview_losses(field, geometry: SlabGeometry, neighbours: CameraNeighbours, uvst: torch.Tensor,
                     target_rgb: torch.Tensor, unit: torch.Tensor, view_index: torch.Tensor, as_seen=None):
    """(L_mp, L_d) for the rays `uvst` of training views `view_index` with predicted depth `unit`.
    `as_seen(colours, view_index)` maps field colours to a photo's appearance (None: identity)."""
    points = geometry.surface_points(uvst, unit)                      # (N, 3)
    centres = rows_of(neighbours.centres, neighbours.index[view_index])  # (N, K, 3)
    weights = neighbours.weights[view_index]                          # (N, K)
    n, k = weights.shape
    ray_uvst, inside = geometry.rays_through(centres, points.unsqueeze(1).expand(n, k, 3))
    weights = weights * inside
    usable = weights.sum(1) > 0
    if not bool(usable.any()):
        zero = unit.sum() * 0.0
        return zero, zero
    weights = weights[usable] / weights[usable].sum(1, keepdim=True)
    rgb_n, unit_n = field(ray_uvst[usable].reshape(-1, 4).clamp(-RANGE_MARGIN, RANGE_MARGIN))
    rgb_n = (rgb_n.view(-1, k, 3) * weights[..., None]).sum(1)
    if as_seen is not None:
        rgb_n = as_seen(rgb_n, view_index[usable])
    unit_n = (unit_n.view(-1, k) * weights).sum(1)
    loss_mp = ((target_rgb[usable] - rgb_n) ** 2).mean()
    loss_d = ((unit.view(-1)[usable] - unit_n) ** 2).mean()
    return loss_mp, loss_d
