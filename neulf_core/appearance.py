"""Per-photo appearance compensation: a learned colour transform for each training view.

Photos of one capture rarely share an exposure and white balance exactly.  A light field
trained on them directly must average the disagreement into its colours (and into ghosts).
Here each training view gets an affine colour transform, rgb' = A_v rgb + b_v, applied to
the field's output during training only; at render time the field's own colour is used
(identity), so the rendered light field has the capture's typical appearance.  A small
penalty keeps the transforms near identity, which pins the otherwise free global colour
scale to the average photo (NeRF-in-the-wild uses per-image embeddings for the same job).
"""

from __future__ import annotations

import torch
from torch import nn


class ViewAppearance(nn.Module):
    def __init__(self, n_views: int, identity_weight: float = 1e-3):
        super().__init__()
        self.matrix = nn.Parameter(torch.eye(3).repeat(n_views, 1, 1))
        self.offset = nn.Parameter(torch.zeros(n_views, 3))
        self.identity_weight = identity_weight

    def forward(self, rgb: torch.Tensor, view_index: torch.Tensor) -> torch.Tensor:
        """(N, 3) field colours seen through the photos' transforms of `view_index` (N,)."""
        matrix = self.matrix[view_index]
        return torch.bmm(matrix, rgb.unsqueeze(-1)).squeeze(-1) + self.offset[view_index]

    def regularisation(self) -> torch.Tensor:
        eye = torch.eye(3, device=self.matrix.device)
        return self.identity_weight * (((self.matrix - eye) ** 2).mean() + (self.offset ** 2).mean())
