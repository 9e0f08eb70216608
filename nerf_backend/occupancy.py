"""An occupancy grid over the scene's box: where the field can have density, so samples in
empty space are skipped (Instant-NGP's and nerfacc's idea).

Cells coincide with the grid field's cells. A cell is marked occupied when the density at
any of its 8 corners exceeds a threshold; because the field's pre-activation is trilinear
inside a cell and the activation is monotone, that maximum is the maximum over the whole
cell, so a cell holding density above the threshold anywhere is never skipped.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
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
    def update_from_vertex_density(self, vertex_density: Tensor, threshold: float, allowed: Tensor | None = None) -> None:
        """Mark cells whose corner density maximum exceeds ``threshold`` (and, given
        ``allowed [Gx, Gy, Gz]``, only those: a prior that knows where nothing can be).

        ``vertex_density`` is ``[Gx+1, Gy+1, Gz+1]``: the density at the cells' corners."""
        expected = tuple(c + 1 for c in self.cells)
        if tuple(vertex_density.shape) != expected:
            raise ValueError(f"expected {expected} vertex values, got {tuple(vertex_density.shape)}")
        corner_max = F.max_pool3d(vertex_density[None, None], kernel_size=2, stride=1)[0, 0]
        occupied = corner_max > threshold
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
