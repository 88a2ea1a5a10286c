"""Per-photo appearance compensation: a learned colour transform for each training view.

Photos of one capture rarely share an exposure and white balance exactly.  A light field
trained on them directly must average the disagreement into its colours (and into ghosts).
Here each training view gets an affine colour transform, rgb' = A_v rgb + b_v, applied to
the field's output during training only; at render time the field's own colour is used
(identity), so the rendered light field has the capture's typical appearance: the
transforms are centred on the identity (their mean is fixed), which pins the otherwise free
global colour to the average photo, and a small penalty keeps each near identity
(NeRF-in-the-wild uses per-image embeddings for the same job).
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

    def transforms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The per-photo (matrix, offset), centred so that their mean is the identity: the
        field's own colours (what renders) are then the average photo's, not whatever
        global colour the optimiser happened to drift to."""
        eye = torch.eye(3, device=self.matrix.device)
        return self.matrix - self.matrix.mean(0) + eye, self.offset - self.offset.mean(0)

    def forward(self, rgb: torch.Tensor, view_index: torch.Tensor) -> torch.Tensor:
        """(N, 3) field colours seen through the photos' transforms of `view_index` (N,)."""
        matrix, offset = self.transforms()
        return torch.bmm(matrix[view_index], rgb.unsqueeze(-1)).squeeze(-1) + offset[view_index]

    def regularisation(self) -> torch.Tensor:
        eye = torch.eye(3, device=self.matrix.device)
        return self.identity_weight * (((self.matrix - eye) ** 2).mean() + (self.offset ** 2).mean())
