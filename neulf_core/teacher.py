"""The classic plane sweep as a depth teacher for the fast field.

The fast field's disparity comes from small factorised planes that gradient descent shapes
only through the texture's local gradient: left alone it settles on a smooth depth with a
fattened band around depth edges and wrong matches on repeated texture.  The per-pixel
plane sweep over the nearest training photos (classic.py) finds a sharper depth in a
fraction of a second per view with no training (measured effect: docs/DEPTH.md).  Each
training view is swept from its k nearest *other* training views; early in training the
field's depth (as a unit in [0, 1], uniform in disparity between the slab's near and far)
is pulled toward it where the sweep is confident, and the pull fades out so photometric
training has the last word.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .classic import ClassicLightField
from .dataset import view_uvst
from .memo import inputs_key, kept
from .scene import scaled_size
from .slab import Slab

# Pull strength at the start, and the fraction of the budget over which it fades to zero:
# a gentle pull keeps the depth gain without the PSNR cost of a strong one (docs/DEPTH.md).
# The fade was 30 % of the budget until the learning rate fell along a cosine; with it, 20 %
# gives the photometric loss longer with a high rate: at 1000 steps, three seeds, 4 of the
# synthetic scene's photos 27.59 -> 27.67 dB (every seed gains, spread 0.20 -> 0.10), its 7
# +0.02, its 14 -0.01, 6 / 26 of CanClip's +0.05 / -0.01, 18 of HCI's -0.04 dB; at the
# product's setting (1.5 minutes at 480x270, seeds 0 / 1, side by side) CanClip -0.01 / +0.02,
# Statue -0.02 / +0.08, fern +0.05 / -0.09 dB: no change.  15 % cost (HCI's 18 views -0.15 dB, wider spreads).
TEACHER_WEIGHT = 0.002
TEACHER_FADE = 0.2
# With at most TEACHER_FEW_VIEWS training photos the pull fades over 40 % instead: the photos
# alone leave a thin foreground structure's depth to chance, and a seed that loses it renders
# it doubled.  At 1000 steps (the stability study's runs, docs/STABILITY.md, thirtieth
# session): 6 of CanClip's photos over six seeds 34.77 +- 0.78 -> 34.80 +- 0.24 dB, the
# synthetic scene's 4 photos over three 28.70 +- 0.19 -> 28.76 +- 0.06; its 7 photos +0.04 dB
# with a wider spread and 13 of CanClip's -0.11, so more photos keep 20 %.  With noisy poses
# (6 runs at 6 / 4 photos) -0.12 dB as rendered and +0.13 with the held-out poses fitted: no
# clear effect, so the longer fade does not wait for the pose check.
TEACHER_FADE_FEW = 0.4
TEACHER_FEW_VIEWS = 6
# Below this many training views the photos constrain the depth less, and the gentle pull
# (what captures of varying exposure keep) strengthens in proportion (1/n): measured before
# the strong pull became the default, at 1000 steps over 3 seeds, 6 of CanClip's views +0.19
# dB, 4 of the synthetic scene's +1.2 dB (docs/STABILITY.md).
TEACHER_FULL_VIEWS = 14
# The pull a capture takes unless it is dense or its photos differ in exposure
# (`strong_pull`).  It was first kept for deep scenes (Slab.is_deep), whose wide disparity
# range leaves photometric descent from the start depth in a worse basin (fern at 2000 steps,
# seeds 0 / 1: 20.77 / 20.82 -> 21.32 / 21.23 dB), because on shallow ones it had cost
# (CanClip -1 dB with an earlier confidence and a longer fade).  With the 4-channel geometry
# it gains on every capture of up to 26 views measured: CanClip 480x270 at 1.5 minutes,
# seeds 0 / 1 / 2, +0.17 / +0.92 / +0.52 dB; Statue +0.59 dB; 6 of CanClip's 26 views at
# 1000 steps 31.26 -> 32.38 dB (docs/DEPTH.md, docs/STABILITY.md).  Not on dense light fields: HCI's 71 training views
# constrain the depth well on their own, and there the strong pull toward a sweep that is
# poor on that scene (BadPix 43-50 %) cost 0.24 dB and 4 points of BadPix (docs/DEPTH.md).
TEACHER_WEIGHT_STRONG = 0.05
# From this many training views on a capture keeps the gentle pull (between CanClip's 26,
# where the strong pull gains, and HCI's 71, where it costs; no scene measured in between).
TEACHER_DENSE_VIEWS = 40
# The sweep's resolution as a fraction of the training images'.
SWEEP_SCALE = 0.5
# A deep scene's sweep is held to this many pixels per view: its strong pull needs no finer
# one (fern swept at a quarter of its 504x378 training size: 21.35 dB at 2000 steps, against
# 21.32 at half), and fern's sweep then takes about 4 s instead of 14.5 s of the budget.
DEEP_SWEEP_PIXELS = 16_000


def sweep_scale_for(train_views, scale: float, slab: Slab) -> float:
    """The sweep's resolution as a fraction of the training images'."""
    if not slab.is_deep:
        return SWEEP_SCALE
    width, height = scaled_size(max(v.size for v in train_views), scale)
    return min(SWEEP_SCALE, (DEEP_SWEEP_PIXELS / (width * height)) ** 0.5)


def sweep_photo_scale(train_views, scale: float, slab: Slab, sweep_scale: float | None = None) -> float:
    """The scale the sweep reads the photos at, for training at `scale` (`sweep_scale` of it, by
    default sweep_scale_for's)."""
    return scale * (sweep_scale_for(train_views, scale, slab) if sweep_scale is None else sweep_scale)


def sweep_depth_targets(train_views, slab: Slab, scale: float, device="cpu", on_view=None,
                        sweep_scale: float | None = None, representable=None,
                        photos: list | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """compute_sweep_depth_targets, or, within a training call (memo.kept_while_training) and
    for the same inputs as its last sweep, that result again (copies) without sweeping: a
    model's members and the better-of-two-starts rule train the same photos again, and each
    recomputed the same sweep -- about 5 s of HCI's 28 s run at the stability study's 1000
    steps, one thread (its two members of half the batch: 51.7 -> 46.9 s, every PSNR to the
    digit; docs/MEMBERS.md).  The targets are one float pair per training ray (HCI's 4.6 M
    rays: 37 MB), a quarter of what the rays themselves hold."""
    key = inputs_key(train_views, slab.to_dict(), scale, sweep_scale, str(torch.device(device)))
    unit, confidence = kept("sweep", key, lambda: compute_sweep_depth_targets(
        train_views, slab, scale, device, on_view, sweep_scale, representable, photos))
    return unit.clone(), confidence.clone()


def compute_sweep_depth_targets(train_views, slab: Slab, scale: float, device="cpu", on_view=None,
                                sweep_scale: float | None = None, representable=None,
                                photos: list | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(unit depth, confidence) per training ray, in build_rayset's order (views in turn,
    row-major pixels, the rays that cross the slab: `representable`, build_rayset's masks of
    them, or traced again where None).  The sweep runs at `sweep_scale` of the
    training resolution (default: half, fewer pixels on deep scenes -- a prior needs no more,
    and a quarter of the pixels is a quarter of the time) and each training pixel takes the
    value of the sweep pixel it falls in.  `photos`: the photos at sweep_photo_scale where
    build_rayset has read them with the training ones (else read here)."""
    small = sweep_photo_scale(train_views, scale, slab, sweep_scale)
    classic = ClassicLightField(train_views, slab, small, device=device, photos=photos)
    units, confidences = [], []
    for i, view in enumerate(train_views):
        _, sweep = classic.render_view(view, small, exclude=i, with_depth=True)
        coarse = view.scaled_camera(small)
        fine = view.scaled_camera(scale)
        maps = torch.stack([sweep.unit, _confidence(sweep)]).reshape(1, 2, int(coarse.height), int(coarse.width))
        maps = F.interpolate(maps, size=(int(fine.height), int(fine.width)), mode="nearest").reshape(2, -1)
        valid = representable[i] if representable is not None else view_uvst(view, slab, scale)[1]
        valid = torch.as_tensor(valid, device=maps.device).reshape(-1)
        units.append(maps[0][valid])
        confidences.append(maps[1][valid])
        if on_view is not None:
            on_view(i, len(train_views), view)
    return torch.cat(units).float(), torch.cat(confidences).float()


def _confidence(sweep) -> torch.Tensor:
    """How distinct the best depth's match is: 1 - best cost / mean cost over the depths.  A
    textured surface matches at one depth only (near 1); a flat or uniformly coloured one
    matches everywhere (near 0), and an occluded one nowhere (the cost stays near the mean).
    A pixel that fewer than two of the other photos see at its depth (the frame's edge, where
    one photo agrees with itself) gets none."""
    distinct = (1 - sweep.cost / sweep.mean_cost.clamp_min(1e-8)).clamp(0, 1)
    return distinct * (sweep.seen >= 2).float()


def strong_pull(n_views: int, appearance: bool) -> bool:
    """Whether training takes the strong pull: below TEACHER_DENSE_VIEWS training views, unless
    the photos differ in exposure (`--appearance`): the sweep compares raw colours across
    photos, and with exposure jitter the strong pull cost 0.4 dB of colour-matched PSNR in the
    stability study (docs/STABILITY.md); those captures keep the gentle pull, stronger for
    fewer views."""
    return n_views < TEACHER_DENSE_VIEWS and not appearance


def teacher_fade(n_views: int) -> float:
    """The fraction of the budget over which the pull fades to zero, for n_views training views."""
    return TEACHER_FADE_FEW if n_views <= TEACHER_FEW_VIEWS else TEACHER_FADE


def teacher_weight(fraction: float, n_views: int = TEACHER_FULL_VIEWS, strong: bool = False) -> float:
    """The pull at this fraction of the budget, for a capture of n_views training views,
    gentle or strong (`strong_pull`)."""
    start = TEACHER_WEIGHT * max(1.0, TEACHER_FULL_VIEWS / max(1, n_views))
    if strong:
        start = max(start, TEACHER_WEIGHT_STRONG)
    return start * max(0.0, 1.0 - fraction / teacher_fade(n_views))


def teacher_loss(unit: torch.Tensor, target: torch.Tensor, confidence: torch.Tensor) -> torch.Tensor:
    return (confidence * (unit.reshape(-1) - target).abs()).mean()
