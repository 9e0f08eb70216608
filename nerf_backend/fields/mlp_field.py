"""The NeRF field: an MLP from (position, direction) to (density, colour).

Density depends on position only; colour on position and, when the field is
view-dependent, on the viewing direction (the paper's Fig. 3 architecture).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..field_components.encodings import PositionalEncoding


@dataclass(frozen=True)
class FieldConfig:
    """Shape of the MLP. The defaults are the paper's."""

    depth: int = 8
    width: int = 256
    # Layers (0-based) whose input gets the encoded position concatenated: (5,) feeds it
    # with the fifth layer's activation into the sixth, as the paper's Fig. 7.
    skips: tuple[int, ...] = (5,)
    position_frequencies: int = 10
    direction_frequencies: int = 4
    view_dependent: bool = True
    colour_width: int = 128
    # "relu" is the paper's; "softplus" (shifted) keeps gradients alive for empty-looking
    # starts (PROTOCOL: ReLU density can die into an all-white scene).
    density_activation: str = "relu"


class NerfField(nn.Module):
    """``forward(positions [N,3], directions [N,3]) -> (density [N], rgb [N,3])``.

    Example:
        >>> field = NerfField(FieldConfig(depth=2, width=16, skips=()))
        >>> sigma, rgb = field(torch.zeros(4, 3), torch.tensor([[0.0, 0.0, 1.0]] * 4))
        >>> sigma.shape, rgb.shape
        (torch.Size([4]), torch.Size([4, 3]))
    """

    def __init__(self, config: FieldConfig) -> None:
        super().__init__()
        self.config = config
        self.position_encoding = PositionalEncoding(3, config.position_frequencies)
        self.direction_encoding = PositionalEncoding(3, config.direction_frequencies)
        in_dims = self.position_encoding.out_dims
        layers = []
        for i in range(config.depth):
            layer_in = config.width if i > 0 else in_dims
            if i in config.skips:
                layer_in += in_dims
            layers.append(nn.Linear(layer_in, config.width))
        self.trunk = nn.ModuleList(layers)
        self.density_head = nn.Linear(config.width, 1)
        if config.view_dependent:
            self.feature = nn.Linear(config.width, config.width)
            self.colour_hidden = nn.Linear(config.width + self.direction_encoding.out_dims, config.colour_width)
            self.colour_head = nn.Linear(config.colour_width, 3)
        else:
            self.colour_head = nn.Linear(config.width, 3)

    def density_features(self, positions: Tensor) -> tuple[Tensor, Tensor]:
        """Density ``[N]`` and the trunk's features ``[N, width]`` at ``positions``."""
        encoded = self.position_encoding(positions)
        h = encoded
        for i, layer in enumerate(self.trunk):
            if i in self.config.skips:
                h = torch.cat([h, encoded], dim=-1)
            h = F.relu(layer(h))
        # Volume rendering runs in float32 whatever precision autocast ran the layers in.
        raw = self.density_head(h).squeeze(-1).float()
        if self.config.density_activation == "relu":
            density = F.relu(raw)
        elif self.config.density_activation == "softplus":
            density = F.softplus(raw - 1.0)
        else:
            raise ValueError(f"unknown density activation {self.config.density_activation!r}")
        return density, h

    def forward(self, positions: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        density, h = self.density_features(positions)
        if self.config.view_dependent:
            h = torch.cat([self.feature(h), self.direction_encoding(directions)], dim=-1)
            h = F.relu(self.colour_hidden(h))
        rgb = torch.sigmoid(self.colour_head(h).float())
        return density, rgb
