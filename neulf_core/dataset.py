"""Training rays held compactly: (u, v, s, t) as float32 (or float16) and colours as uint8.

A 40-view 960x540 capture is 20.7 M rays: 20.7 M x (16 + 3 + 2) bytes = 435 MB, which
fits a laptop; float16 coordinates bring it to 270 MB.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .rays import view_rays
from .scene import View
from .slab import Slab


@dataclass
class RaySet:
    uvst: torch.Tensor        # (N, 4) normalised coordinates
    rgb: torch.Tensor         # (N, 3) uint8
    view_index: torch.Tensor  # (N,) int16, index into `names`
    names: list[str]

    def __len__(self) -> int:
        return int(self.rgb.shape[0])

    def to(self, device) -> "RaySet":
        return RaySet(self.uvst.to(device), self.rgb.to(device), self.view_index.to(device), self.names)

    def batch(self, index: torch.Tensor):
        """(uvst float32, rgb float32 in [0, 1]) for ray indices `index`."""
        return self.uvst[index].float(), self.rgb[index].float() / 255.0

    def subset(self, count: int, generator: torch.Generator) -> "RaySet":
        if count >= len(self):
            return self
        index = torch.randperm(len(self), generator=generator)[:count].to(self.rgb.device)
        return RaySet(self.uvst[index], self.rgb[index], self.view_index[index], self.names)


def view_uvst(view: View, slab: Slab, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(H*W, 4) normalised (u, v, s, t) of a view's pixels and the mask of representable rays."""
    camera = view.scaled_camera(scale)
    origin, directions = view_rays(camera, view.R, view.t)
    uvst, valid = slab.rays_to_uvst(torch.from_numpy(origin), torch.from_numpy(directions))
    return uvst.float(), valid


def build_rayset(views: list[View], slab: Slab, scale: float, coord_dtype=torch.float32, on_view=None) -> RaySet:
    uvst_parts, rgb_parts, index_parts = [], [], []
    for i, view in enumerate(views):
        uvst, valid = view_uvst(view, slab, scale)
        rgb = torch.from_numpy(view.load_image(scale).reshape(-1, 3).copy())
        uvst_parts.append(uvst[valid].to(coord_dtype))
        rgb_parts.append(rgb[valid])
        index_parts.append(torch.full((int(valid.sum()),), i, dtype=torch.int16))
        if on_view is not None:
            on_view(i, len(views), view)
    return RaySet(torch.cat(uvst_parts), torch.cat(rgb_parts), torch.cat(index_parts), [v.name for v in views])


def mean_colour(rays: RaySet) -> np.ndarray:
    return (rays.rgb.float().mean(0) / 255.0).cpu().numpy()
