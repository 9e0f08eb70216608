"""Multiresolution hash encoding (Müller et al. 2022, Instant-NGP), in plain PyTorch so it
runs wherever PyTorch does (CPU, CUDA, MPS) with no compiled extension.

``levels`` grids from ``base_resolution`` to ``max_resolution`` cells a side, in geometric
steps. Each level stores ``features`` numbers per vertex in a table of ``2**log2_table_size``
rows: coarse levels that fit are indexed directly, finer ones through the paper's spatial
hash (``x·1 ⊕ y·2654435761 ⊕ z·805459861`` mod table size), collisions resolved by training.
A point's encoding is the trilinear interpolation of its cell's 8 corners at every level.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

_PRIMES = (1, 2654435761, 805459861)


def level_resolutions(levels: int, base_resolution: int, max_resolution: int) -> list[int]:
    """Cells a side of each level: geometric from ``base_resolution`` to ``max_resolution``.

    Example:
        >>> level_resolutions(4, 16, 128)
        [16, 32, 64, 128]
    """
    if levels == 1:
        return [base_resolution]
    growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (levels - 1))
    return [int(round(base_resolution * growth**level)) for level in range(levels)]


class HashEncoding(nn.Module):
    """``forward(u [P, 3] in [0, 1]) -> [P, levels · features]``.

    Example:
        >>> encoding = HashEncoding(levels=4, features=2, log2_table_size=12, base_resolution=4, max_resolution=32)
        >>> encoding(torch.rand(5, 3)).shape
        torch.Size([5, 8])
    """

    def __init__(self, levels: int = 16, features: int = 2, log2_table_size: int = 16,
                 base_resolution: int = 16, max_resolution: int = 512) -> None:
        super().__init__()
        self.levels, self.features = levels, features
        self.table_size = 2**log2_table_size
        resolutions = level_resolutions(levels, base_resolution, max_resolution)
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=torch.float32), persistent=False)
        # The coarse levels whose (res+1)³ vertices fit in a table are indexed directly (no
        # collisions); levels are in increasing resolution, so those come first.
        self.dense_levels = sum(1 for r in resolutions if (r + 1) ** 3 <= self.table_size)
        # Instant-NGP's initialisation: small uniform values, so the field starts smooth.
        self.tables = nn.Parameter(torch.empty(levels * self.table_size, features).uniform_(-1e-4, 1e-4))

    @property
    def out_dims(self) -> int:
        return self.levels * self.features

    def _rows(self, vertex: Tensor, first_level: int, dense: bool) -> Tensor:
        """Table rows ``[P, L', 2, 2, 2]`` of the cell corners, from each axis's near and far
        vertex ``vertex [P, L', 3, 2]`` (levels ``first_level`` on). Each axis's term is
        formed before the 8 corners are: ``(a ⊕ b ⊕ c) mod 2^k = (a mod 2^k) ⊕ (b mod 2^k) ⊕
        (c mod 2^k)``, and a level's table offset (a multiple of 2^k) is or-ed into one term."""
        count = vertex.shape[1]
        mask = self.table_size - 1
        offsets = (torch.arange(first_level, first_level + count, device=vertex.device) * self.table_size)
        x, y, z = vertex.unbind(2)  # each [P, L', 2]
        if dense:
            side = (self.resolutions[first_level:first_level + count].long() + 1)[None, :, None]
            x, y, z = x + offsets[None, :, None], y * side, z * side * side
            rows = x[..., :, None, None] + y[..., None, :, None] + z[..., None, None, :]
        else:
            x = ((x * _PRIMES[0]) & mask) | offsets[None, :, None]
            y, z = (y * _PRIMES[1]) & mask, (z * _PRIMES[2]) & mask
            rows = x[..., :, None, None] ^ y[..., None, :, None] ^ z[..., None, None, :]
        return rows

    def forward(self, unit_points: Tensor) -> Tensor:
        points = unit_points.float().clamp(0.0, 1.0)
        resolutions = self.resolutions[None, :, None]
        scaled = points[:, None, :] * resolutions  # [P, L, 3]
        cell = torch.minimum(scaled.floor(), resolutions - 1)
        fraction = scaled - cell  # in [0, 1]
        near = cell.long()
        vertex = torch.stack([near, near + 1], dim=-1)  # per axis, near and far vertex [P, L, 3, 2]
        split = self.dense_levels
        rows = torch.cat([self._rows(vertex[:, :split], 0, dense=True),
                          self._rows(vertex[:, split:], split, dense=False)], dim=1)
        wx, wy, wz = torch.stack([1.0 - fraction, fraction], dim=-1).unbind(2)  # each [P, L, 2]
        weights = wx[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :]  # [P, L, 2, 2, 2]
        values = self.tables.index_select(0, rows.reshape(-1)).view(-1, 8, self.features)
        encoded = torch.bmm(weights.reshape(-1, 1, 8), values)  # trilinear interpolation at every level
        return encoded.reshape(points.shape[0], self.out_dims)
