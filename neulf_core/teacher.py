"""The classic plane sweep as a depth teacher for the fast field.

The fast field's disparity comes from small factorised planes that gradient descent shapes
only through the texture's local gradient: on scenes of thin, overlapping structure (fern
fronds) it settles on a blurred depth and the texture averages the views.  The per-pixel
plane sweep over the nearest training photos (classic.py) finds a sharp depth in about a
second per view with no training.  Each training view is swept from its k nearest *other*
training views; early in training the field's depth (as a unit in [0, 1], uniform in
disparity between the slab's near and far) is pulled toward it, where the sweep is
confident, and the pull fades out so photometric training has the last word.
"""

from __future__ import annotations

import torch

from .classic import ClassicLightField
from .dataset import view_uvst
from .slab import Slab

# Pull strength at the start, and the fraction of the budget over which it fades to zero.
TEACHER_WEIGHT = 0.05
TEACHER_FADE = 0.5


def sweep_depth_targets(train_views, slab: Slab, scale: float, device="cpu", on_view=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit depth, confidence) per training ray, in build_rayset's order (views in turn,
    row-major pixels, the rays that cross the slab)."""
    classic = ClassicLightField(train_views, slab, scale, device=device)
    units, confidences = [], []
    for i, view in enumerate(train_views):
        camera = view.scaled_camera(scale)
        _, unit, cost = classic.render_view(view, scale, exclude=i, with_depth=True)
        _, valid = view_uvst(view, slab, scale)
        valid = torch.as_tensor(valid, device=unit.device).reshape(-1)
        units.append(unit[valid])
        confidences.append(_confidence(cost, int(camera.width), int(camera.height))[valid])
        if on_view is not None:
            on_view(i, len(train_views), view)
    return torch.cat(units).float(), torch.cat(confidences).float()


def _confidence(cost: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Trust low photo-consistency cost (a match), relative to the view's typical cost:
    textureless or occluded pixels match badly or everywhere and get little weight."""
    typical = cost.median().clamp_min(1e-8)
    return torch.exp(-cost / typical)


def teacher_weight(fraction: float) -> float:
    return TEACHER_WEIGHT * max(0.0, 1.0 - fraction / TEACHER_FADE)


def teacher_loss(unit: torch.Tensor, target: torch.Tensor, confidence: torch.Tensor) -> torch.Tensor:
    return (confidence * (unit.reshape(-1) - target).abs()).mean()
