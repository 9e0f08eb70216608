"""An occupancy grid over the scene's box: where the field can have density, so samples in
empty space are skipped (Instant-NGP's and nerfacc's idea).

A cell is marked occupied when the field's estimate of its largest density exceeds a
threshold. The grid field's estimate is exact (its cells are these cells, and the maximum
over a cell's corners bounds it), so with that field a cell holding density above the
threshold anywhere is never skipped; other fields give an estimate (``MarchableField``).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class OccupancyGrid(nn.Module):
    """``occupied [Gx, Gy, Gz]`` cells over ``[box_min, box_max]``; all occupied until updated
    (``cells``: per axis, or an int for the same on every axis).

    A module only so that ``.to(device)`` and ``state_dict()`` carry the grid along."""

    def __init__(self, box_min: Tensor, box_max: Tensor, cells: tuple[int, int, int] | int) -> None:
        super().__init__()
        self.cells = (cells,) * 3 if isinstance(cells, int) else tuple(cells)
        self.register_buffer("box_min", box_min.detach().clone())
        self.register_buffer("box_max", box_max.detach().clone())
        self.register_buffer("occupied", torch.ones(self.cells, dtype=torch.bool))
        self.register_buffer("_cells_tensor", torch.tensor(self.cells), persistent=False)

    @torch.no_grad()
    def update(self, cell_max_density: Tensor, threshold: float, allowed: Tensor | None = None) -> None:
        """Mark the cells whose largest density ``[Gx, Gy, Gz]`` exceeds ``threshold`` (and,
        given ``allowed [Gx, Gy, Gz]``, only those: a prior that knows where nothing can be)."""
        if tuple(cell_max_density.shape) != self.cells:
            raise ValueError(f"expected {self.cells} cell values, got {tuple(cell_max_density.shape)}")
        occupied = cell_max_density > threshold
        self.occupied.copy_(occupied if allowed is None else occupied & allowed)

    def cell_index(self, points: Tensor) -> Tensor:
        """Integer cell coordinates ``[P, 3]`` of world points (clamped to the grid)."""
        unit = (points - self.box_min) / (self.box_max - self.box_min)
        return (unit * self._cells_tensor).floor().long().clamp_min(0).minimum(self._cells_tensor - 1)

    def query(self, points: Tensor) -> Tensor:
        """True where a world point lies in an occupied cell (points outside the box: False)."""
        inside = ((points >= self.box_min) & (points <= self.box_max)).all(dim=-1)
        ijk = self.cell_index(points)
        return inside & self.occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    @property
    def occupied_fraction(self) -> float:
        return float(self.occupied.float().mean())
