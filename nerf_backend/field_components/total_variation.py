"""Total variation of a sparse voxel grid (Plenoxels' regulariser): the mean squared difference
between a vertex and its next neighbour along each axis, over a random set of kept vertices a
step, each channel weighted.

Its gradient goes, like the grid's read, only into the rows it touched: into the grid's row
buffers where ``SparseRowAdam`` gave it some (so a step stays sparse), else dense through
autograd.

Example:
    >>> from nerf_backend.field_components.sparse_grid import SparseVoxelGrid
    >>> grid = SparseVoxelGrid(channels=1, vertices=(4, 4, 4))
    >>> with torch.no_grad():
    ...     _ = grid.values[:, 0].copy_(torch.arange(64.0) % 4)  # rises by 1 along z
    >>> weights = torch.zeros(8); weights[0] = 1.0
    >>> round(total_variation(grid, weights, vertices=64).item(), 3)  # 48 of 64 have a z neighbour
    0.75
"""

from __future__ import annotations

import torch
from torch import Tensor

from .sparse_grid import SparseVoxelGrid


def total_variation(grid: SparseVoxelGrid, channel_weights: Tensor, vertices: int,
                    generator: torch.Generator | None = None) -> Tensor:
    """Σ_c w_c Σ_pairs (v_a,c − v_b,c)² / ``vertices`` over ``vertices`` kept vertices drawn at
    random (all of them, in order, where there are no more), each paired with its kept
    neighbour at +1 along each axis; ``channel_weights`` has the grid's padded width."""
    device = grid.links.device
    if vertices >= grid.rows:
        rows = torch.arange(grid.rows, device=device)
    else:  # drawn where the generator lives (the trainer's is on the model's device)
        drawn_on = generator.device if generator is not None else device
        rows = torch.randint(grid.rows, (vertices,), generator=generator, device=drawn_on).to(device)
    first, second = neighbour_pairs(grid, rows)
    return _TotalVariation.apply(grid.values, grid, first, second, channel_weights, max(1, rows.numel()))


def neighbour_pairs(grid: SparseVoxelGrid, rows: Tensor) -> tuple[Tensor, Tensor]:
    """The pairs (row, its kept neighbour's row) along x, then y, then z."""
    coordinates = vertex_coordinates(grid).index_select(0, rows)
    firsts, seconds = [], []
    for axis in range(3):
        neighbour = coordinates.clone()
        neighbour[:, axis] += 1
        inside = neighbour[:, axis] < grid.vertices[axis]
        neighbour = neighbour[inside]
        linked = grid.links[neighbour[:, 0], neighbour[:, 1], neighbour[:, 2]].long()
        firsts.append(rows[inside][linked >= 0])
        seconds.append(linked[linked >= 0])
    return torch.cat(firsts), torch.cat(seconds)


def vertex_coordinates(grid: SparseVoxelGrid) -> Tensor:
    """Each row's vertex ``[rows, 3]`` (long), kept with the grid until its links change."""
    key = (grid.links.data_ptr(), tuple(grid.links.shape))
    cached = getattr(grid, "_coordinates", None)
    if cached is None or cached[0] != key:
        coordinates = torch.empty((grid.rows, 3), dtype=torch.long, device=grid.links.device)
        kept = grid.links >= 0
        coordinates[grid.links[kept].long()] = kept.nonzero()
        cached = grid._coordinates = (key, coordinates)
    return cached[1]


class _TotalVariation(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values: Tensor, grid: SparseVoxelGrid, first: Tensor, second: Tensor, weights: Tensor,
                count: int) -> Tensor:
        difference = values.index_select(0, first) - values.index_select(0, second)
        ctx.grid, ctx.count = grid, count
        ctx.save_for_backward(first, second, difference, weights, values)
        return (difference.square() * weights).sum() / count

    @staticmethod
    def backward(ctx, grad: Tensor):
        first, second, difference, weights, values = ctx.saved_tensors
        toward = difference * weights * (2.0 / ctx.count) * grad
        sink = getattr(ctx.grid, "row_gradients", None)
        if sink is not None and sink.serves([values]):
            into, marks = sink.gradients[0], sink.marks[0]
            into.index_add_(0, first, toward)
            into.index_add_(0, second, -toward)
            marks[first] = 1
            marks[second] = 1
            return None, None, None, None, None, None
        dense = torch.zeros_like(values)
        dense.index_add_(0, first, toward)
        dense.index_add_(0, second, -toward)
        return dense, None, None, None, None, None
