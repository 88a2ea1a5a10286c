"""NeuLF's MLP: the paper's network (20 x 256) and the authors' code default (8 x 256).

Paper (Sec. 4.1): the normalised 4D input passes through `depth` fully connected ReLU
layers of `width` channels, the input re-concatenated every 4 layers starting with the
fifth; one more layer gives a 256-d feature that splits into a colour branch and a depth
branch, each a 128-channel ReLU layer and a sigmoid output (3 and 1 channels).

The authors' released code differs: Linear(4, 256) + ReLU embeds the input first, the skip
re-concatenates that 256-d embedding (not the raw 4D input), and the colour head is
Linear(256, 256), Linear(256, 128) + ReLU, Linear(128, 3) + sigmoid.  `skip="embedding"`
reproduces that.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from . import register


@dataclass
class MLPConfig:
    depth: int = 20          # number of hidden ReLU layers
    width: int = 256
    skip_every: int = 4      # re-concatenate the input before layers 5, 9, 13, ...
    skip: str = "input"      # "input": the raw 4D coordinate (paper); "embedding": the first layer's output (code)
    head_width: int = 128


class NeuLFMLP(nn.Module):
    def __init__(self, config: MLPConfig):
        super().__init__()
        self.config = config
        skip_width = 4 if config.skip == "input" else config.width
        layers = []
        in_width = 4
        for i in range(config.depth):
            if i > 0 and i % config.skip_every == 0:
                in_width += skip_width
            layers.append(nn.Linear(in_width, config.width))
            in_width = config.width
        self.layers = nn.ModuleList(layers)
        self.feature = nn.Linear(config.width, 256)
        self.colour_head = nn.Sequential(nn.Linear(256, config.head_width), nn.ReLU(), nn.Linear(config.head_width, 3))
        self.depth_head = nn.Sequential(nn.Linear(256, config.head_width), nn.ReLU(), nn.Linear(config.head_width, 1))

    def forward(self, uvst: torch.Tensor):
        h = uvst
        skip_value = uvst
        for i, layer in enumerate(self.layers):
            if i > 0 and i % self.config.skip_every == 0:
                h = torch.cat([h, skip_value], dim=-1)
            h = torch.relu(layer(h))
            if i == 0 and self.config.skip == "embedding":
                skip_value = h
        feature = self.feature(h)
        return torch.sigmoid(self.colour_head(feature)), torch.sigmoid(self.depth_head(feature))


register("mlp", MLPConfig, NeuLFMLP, "NeuLF MLP (paper: 20 x 256; authors' code: 8 x 256 with embedding skips)")
