"""Per-photo appearance compensation: a learned colour transform for each training view.

Photos of one capture rarely share an exposure and white balance exactly.  A light field
trained on them directly must average the disagreement into its colours (and into ghosts).
Here each training view gets an affine colour transform, rgb' = A_v rgb + b_v, applied to
the field's output during training only; at render time the field's own colour is used
(identity), so the rendered light field has the capture's typical appearance: the
transforms are centred on the identity (their mean is fixed), which pins the otherwise free
global colour to the average photo, and a small penalty keeps each near identity
(NeRF-in-the-wild uses per-image embeddings for the same job).

The transform acts on linear light (the sRGB curve undone, applied, and redone, with the
photo's clipping at white), since an exposure or white-balance change is a gain on linear
light, not on sRGB values; and each photo's gain, in stops, starts at its measured exposure,
so the field does not first learn the exposures into its colours and geometry.  Runs saved
before keep the sRGB-space transform they were trained with (`linear_light` False).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .rows import rows_of
from .scene import camera_gaps

# The compensation is on by default when neighbouring photos differ in exposure by at least
# this much (stops; the median over the photos of the difference to the nearest camera's).
# Measured on the training photos (exposure_difference): the project's scene 0.004 stops,
# with its exposures jittered by up to 0.25 / 0.5 / 1 stop 0.078 / 0.164 / 0.334; the real
# captures, whose exposure is fixed, HCI 0.006, fern 0.015, Statue 0.034, CanClip 0.037 (at
# the training scales of the study and benchmarks, and with CanClip's poses perturbed, up to 0.048).
# Where the photos share one exposure the compensation costs (1000 steps, seeds 0 / 1: CanClip
# -0.85 / -1.32 dB, the project's scene -0.19 / -0.10), and at 0.25 stops of jitter it gains
# +1.15 / +1.16 dB as rendered but nothing under NeRF-in-the-wild's protocol (+0.22 / -0.12),
# at 0.5 stops +2.75 / +2.54 as rendered and +0.30 / +0.23 under the protocol.  So the threshold
# stays well above where fixed exposures and changing content lie (docs/STABILITY.md, "Exposure").
# (Those costs are the sRGB-space transform's; the linear-light one forced on for CanClip's fixed
# exposure costs less: 1000 steps, seeds 0 / 1, 36.37 -> 35.78 / 35.68 dB, against 35.01 / 34.83.)
EXPOSURE_DIFFERENCE_STOPS = 0.1


def srgb_to_linear(srgb: torch.Tensor) -> torch.Tensor:
    """sRGB values in [0, 1] (clamped) to linear light."""
    srgb = srgb.clamp(0.0, 1.0)
    return torch.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: torch.Tensor) -> torch.Tensor:
    """Linear light to sRGB values, clipped to [0, 1] as a photo's pixels are.  (The power
    branch reads a value kept above its threshold, so its gradient stays finite at zero.)"""
    linear = linear.clamp(0.0, 1.0)
    return torch.where(linear <= 0.0031308, linear * 12.92, 1.055 * linear.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


class ViewAppearance(nn.Module):
    """Per photo: a gain in stops (`stops`, linear light only) times a colour matrix, plus an
    offset.  The gains are centred in stops, so the field renders at the photos' typical
    exposure (their mean in stops: the capture's middle exposure); the matrices and offsets
    are centred on the identity, so it renders the average photo's colour balance."""

    def __init__(self, n_views: int, identity_weight: float = 1e-3, linear_light: bool = True):
        super().__init__()
        self.matrix = nn.Parameter(torch.eye(3).repeat(n_views, 1, 1))
        self.offset = nn.Parameter(torch.zeros(n_views, 3))
        if linear_light:
            self.stops = nn.Parameter(torch.zeros(n_views))
        self.identity_weight = identity_weight
        self.linear_light = linear_light

    def start_from_exposures(self, exposures: np.ndarray) -> None:
        """Each photo's gain set to its measured exposure (stops, photo_exposures).  Neighbouring
        photos of a forward-facing capture see nearly the same things, so this is mostly the
        exposure; what is the scene's own brightness the training takes back out.  Without this
        start the field first learns the exposures into its colours and depth (the jittered
        synthetic scene's 14 photos, 1000 steps: NeRF-W's protocol 28.07 dB without it, even at
        five times the learning rate, 28.4-28.5 with it; docs/STABILITY.md)."""
        if not self.linear_light:
            raise ValueError("the exposure start is for the linear-light transform")
        with torch.no_grad():
            self.stops.copy_(torch.as_tensor(np.asarray(exposures, dtype=np.float64), dtype=self.stops.dtype))

    def transforms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The per-photo (matrix, offset), the gain folded into the matrix, centred so that the
        field's own colours (what renders) are the typical photo's, not whatever global colour
        the optimiser happened to drift to."""
        eye = torch.eye(3, device=self.matrix.device)
        matrix = self.matrix - self.matrix.mean(0) + eye
        if self.linear_light:
            matrix = matrix * torch.exp2(self.stops - self.stops.mean())[:, None, None]
        return matrix, self.offset - self.offset.mean(0)

    def forward(self, rgb: torch.Tensor, view_index: torch.Tensor) -> torch.Tensor:
        """(N, 3) field colours seen through the photos' transforms of `view_index` (N,)."""
        matrix, offset = self.transforms()
        colour = srgb_to_linear(rgb) if self.linear_light else rgb
        seen = torch.bmm(rows_of(matrix, view_index), colour.unsqueeze(-1)).squeeze(-1) + rows_of(offset, view_index)
        return linear_to_srgb(seen) if self.linear_light else seen

    def regularisation(self) -> torch.Tensor:
        """A pull of the colour matrices and offsets toward the identity (not of the gains:
        an exposure can be anything, and their centring fixes the global brightness)."""
        eye = torch.eye(3, device=self.matrix.device)
        return self.identity_weight * (((self.matrix - eye) ** 2).mean() + (self.offset ** 2).mean())


def photo_exposures(rgb: torch.Tensor, view_index: torch.Tensor, n_views: int) -> np.ndarray:
    """(n_views,) each photo's exposure in stops: log2 of its mean linear luminance.
    `rgb`: (N, 3) uint8 training colours (sRGB), `view_index`: (N,) their photos."""
    linear = srgb_to_linear(rgb.float() / 255.0)
    luminance = linear @ torch.tensor([0.2126, 0.7152, 0.0722], device=linear.device)
    index = view_index.long()
    sums = torch.zeros(n_views, device=luminance.device).index_add_(0, index, luminance)
    counts = torch.zeros(n_views, device=luminance.device).index_add_(0, index, torch.ones_like(luminance))
    return np.log2((sums / counts.clamp(min=1)).cpu().numpy().astype(np.float64) + 1e-4)


# A photo whose pixels vary by less than this (sRGB levels of 255, standard deviation) is one
# flat colour: a lens cap, a blank frame, a photo of a white wall.  Two black photos among nine
# had cost a model 30 dB (43.7 -> 14.1) while training blamed the poses.
BLANK_PHOTO_LEVELS = 2.0


def blank_photos(rgb: torch.Tensor, view_index: torch.Tensor, n_views: int) -> list[int]:
    """Indices of the photos whose training colours are nearly one flat colour."""
    grey = rgb.float().mean(dim=1)
    index = view_index.long()
    counts = torch.zeros(n_views, device=grey.device).index_add_(0, index, torch.ones_like(grey)).clamp(min=1)
    mean = torch.zeros(n_views, device=grey.device).index_add_(0, index, grey) / counts
    square = torch.zeros(n_views, device=grey.device).index_add_(0, index, grey * grey) / counts
    spread = (square - mean * mean).clamp(min=0).sqrt()
    return [int(i) for i in torch.nonzero(spread < BLANK_PHOTO_LEVELS).flatten().tolist()]


def exposure_difference(exposures: np.ndarray, centres: np.ndarray) -> float:
    """Median over the photos of how far (stops) each one's exposure is from its nearest
    camera's.  Neighbours see nearly the same things, so a fixed exposure keeps this small
    however much the brightness changes across the scene."""
    if len(centres) < 2:
        return 0.0
    return float(np.median(np.abs(exposures - exposures[camera_gaps(centres).argmin(axis=1)])))


def appearance_by_default(difference_stops: float) -> bool:
    return difference_stops >= EXPOSURE_DIFFERENCE_STOPS
