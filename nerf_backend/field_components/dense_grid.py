"""A dense grid of one value per vertex, read trilinearly: what a signed distance field is
stored in (Voxurf, DVGO), where a factorised grid's low rank would round a surface off.

Coordinates are normalised to [-1, 1] (``align_corners=True``: -1 and 1 are the first and
last vertices); ``values`` is laid out ``[1, 1, Nz, Ny, Nx]``, as ``grid_sample`` reads it.

Example:
    >>> grid = DenseGrid(torch.arange(8.0).view(2, 2, 2))  # value at (x, y, z) = 4x + 2y + z
    >>> grid(torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, -1.0]])).tolist()  # the centre; vertex (1, 0, 0)
    [3.5, 4.0]
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

Vertices = tuple[int, int, int]


class DenseGrid(nn.Module):
    """``forward(x [P, 3] in [-1, 1]) -> [P]``, from ``initial [Nx, Ny, Nz]`` vertex values.

    The parameters hold the values divided by ``unit``: an optimiser's step then moves a
    value by its learning rate in that unit (a signed distance's unit is a cell), whatever
    the scene's scale."""

    def __init__(self, initial: Tensor, unit: float = 1.0) -> None:
        super().__init__()
        self.unit = unit
        self.values = nn.Parameter((initial.float() / unit).permute(2, 1, 0).contiguous()[None, None])

    @property
    def vertices(self) -> Vertices:
        nz, ny, nx = self.values.shape[-3:]
        return (nx, ny, nz)

    def forward(self, x: Tensor) -> Tensor:
        return self.read(self.values, x) * self.unit

    @staticmethod
    def read(values: Tensor, x: Tensor) -> Tensor:
        """Trilinear reads of a ``[1, 1, Nz, Ny, Nx]`` volume at normalised points (in the
        volume's own units)."""
        grid = x.reshape(1, -1, 1, 1, 3).to(values.dtype)  # grid_sample's (x, y, z) = (W, H, D)
        return F.grid_sample(values, grid, mode="bilinear", align_corners=True).view(-1)

    def vertex_values(self) -> Tensor:
        """The values ``[Nx, Ny, Nz]`` (with gradients)."""
        return self.values[0, 0].permute(2, 1, 0) * self.unit

    @torch.no_grad()
    def resize(self, vertices: Vertices) -> None:
        """Resample to other vertex counts (trilinear: the same function, more vertices)."""
        nx, ny, nz = vertices
        resized = F.interpolate(self.values.data, size=(nz, ny, nx), mode="trilinear", align_corners=True)
        self.values = nn.Parameter(resized.contiguous())
