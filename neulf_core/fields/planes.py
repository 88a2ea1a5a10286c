"""A fast field: the 4D light field factorised into six 2D feature planes plus a small MLP.

Each of the six axis pairs of (u, v, s, t) gets a feature plane (K-Planes' factorisation
generalised to 4D); a ray's feature is the element-wise product of its six bilinear
samples, at several spatial resolutions, decoded by a tiny MLP.  Why it is shaped so:

- The st plane sits in the scene, so most of a ray's colour is a texture over (s, t):
  the (s, t) plane carries it at high resolution.
- The angular axes (u, v) are observed only at as many points as there are cameras, so
  they get few cells (`angular_res`, tied to the camera count by the trainer); planes that
  mix an angular and a spatial axis model parallax (slanted lines in epipolar images).
- Angular-containing planes start at one, so the initial field is exactly "a texture on
  the st plane" -- classic single-focal-plane light field rendering -- and training adds
  parallax from there; total variation keeps the sparsely observed angular cells smooth.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from . import register

PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))  # uv, us, ut, vs, vt, st
ANGULAR = (0, 1)


@dataclass
class PlanesConfig:
    angular_res: int = 8
    spatial_res: list[int] = field(default_factory=lambda: [64, 128, 256])
    channels: int = 16
    hidden: int = 64
    hidden_layers: int = 2
    tv_weight: float = 1e-3       # total variation on planes that include an angular axis
    tv_weight_spatial: float = 0.0


class PlanesField(nn.Module):
    def __init__(self, config: PlanesConfig):
        super().__init__()
        self.config = config
        self.scales = nn.ModuleList()
        for res in config.spatial_res:
            planes = nn.ParameterList()
            for a, b in PAIRS:
                size_a = config.angular_res if a in ANGULAR else res
                size_b = config.angular_res if b in ANGULAR else res
                # grid_sample indexes (H, W) = (axis a, axis b).
                if a in ANGULAR or b in ANGULAR:
                    init = torch.ones(1, config.channels, size_a, size_b)
                else:
                    init = torch.empty(1, config.channels, size_a, size_b).uniform_(0.1, 0.5)
                planes.append(nn.Parameter(init))
            self.scales.append(planes)
        layers: list[nn.Module] = []
        width = config.channels * len(config.spatial_res)
        for _ in range(config.hidden_layers):
            layers += [nn.Linear(width, config.hidden), nn.ReLU()]
            width = config.hidden
        layers.append(nn.Linear(width, 4))
        self.decoder = nn.Sequential(*layers)

    def features(self, uvst: torch.Tensor) -> torch.Tensor:
        n = uvst.shape[0]
        per_scale = []
        for planes in self.scales:
            product = None
            for plane, (a, b) in zip(planes, PAIRS):
                # grid_sample wants (x, y) = (width index, height index) = (axis b, axis a).
                grid = torch.stack([uvst[:, b], uvst[:, a]], dim=-1).view(1, n, 1, 2)
                sample = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True)
                sample = sample.view(plane.shape[1], n)
                product = sample if product is None else product * sample
            per_scale.append(product)
        return torch.cat(per_scale, dim=0).t()

    def forward(self, uvst: torch.Tensor):
        out = self.decoder(self.features(uvst))
        return torch.sigmoid(out[:, :3]), torch.sigmoid(out[:, 3:4])

    def regularisation(self) -> torch.Tensor:
        """Total variation of the planes: strong on angular planes (sparsely observed).

        Planes of one shape and weight are stacked and taken together: the same sum of
        per-plane means, in a third of the operations.  A training step was bound by their
        count, not their arithmetic (docs/BENCHMARKS.md, "The GPU targets")."""
        groups: dict[tuple, list[torch.Tensor]] = {}
        for planes in self.scales:
            for plane, (a, b) in zip(planes, PAIRS):
                weight = self.config.tv_weight if (a in ANGULAR or b in ANGULAR) else self.config.tv_weight_spatial
                if weight != 0:
                    groups.setdefault((weight, tuple(plane.shape)), []).append(plane)
        total = self.scales[0][0].new_zeros(())
        for (weight, _), planes in groups.items():
            stacked = planes[0] if len(planes) == 1 else torch.cat(planes, 0)
            total = total + weight * len(planes) * total_variation(stacked)
        return total

    def param_groups(self, lr: float):
        """Grids learn with a larger step than the decoder (as in grid-based radiance fields)."""
        return [
            {"params": list(self.scales.parameters()), "lr": lr * 10.0, "name": "planes"},
            {"params": list(self.decoder.parameters()), "lr": lr, "name": "decoder"},
        ]


def total_variation(planes: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between neighbouring cells of (..., H, W) feature planes."""
    return _TotalVariation.apply(planes)


class _TotalVariation(torch.autograd.Function):
    """The total variation with its gradient written out: each difference pushes its two cells
    apart by the same amount.  Autograd's version of the same (slices, squares, means and
    their backward passes, each slice's gradient a zero-filled copy) took twice as long: the
    depth layers' prior, 8 x 2 x 128 x 128 cells, 2.8 against 1.3 ms per step on one CPU
    thread, the same gradient to 1e-7 (docs/BENCHMARKS.md, "The geometry planes' smoothness
    prior")."""

    @staticmethod
    def forward(ctx, planes: torch.Tensor) -> torch.Tensor:
        dh = planes[..., 1:, :] - planes[..., :-1, :]
        dw = planes[..., :, 1:] - planes[..., :, :-1]
        ctx.save_for_backward(dh, dw)
        return dh.square().mean() + dw.square().mean()

    @staticmethod
    def backward(ctx, grad_output: torch.Tensor) -> torch.Tensor:
        dh, dw = ctx.saved_tensors
        gh = dh * (2.0 * grad_output / dh.numel())
        gw = dw * (2.0 * grad_output / dw.numel())
        grad = dh.new_zeros(dh.shape[:-2] + (dh.shape[-2] + 1, dh.shape[-1]))
        grad[..., 1:, :] += gh
        grad[..., :-1, :] -= gh
        grad[..., :, 1:] += gw
        grad[..., :, :-1] -= gw
        return grad


register("planes", PlanesConfig, PlanesField, "six factorised (u,v,s,t) feature planes + tiny MLP (fast)")
