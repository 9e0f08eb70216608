"""KiloNeRF (Reiser et al. 2021): a trained model distilled into a grid of tiny networks, one a
cell (the paper: lego in 9×16×10 cells), each two hidden layers of 32 over the position's
encoding, then the view direction's for the colour. Rendered by the same march as the
product's models (its occupancy grid and early termination): ``density_fn`` and ``ray_colour``
are what the march is given.

The march asks for density at every sample and colour at the samples light still reaches, so
the trunk (the position's two layers) runs again for those: the price of keeping the march
unchanged, counted in ``flops_per_sample``.

Example:
    >>> from nerf_backend.core.scene_bounds import SceneBounds
    >>> kilo = KiloNerf(SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), cells=(2, 2, 2))
    >>> points = torch.rand(10, 3) * 2 - 1
    >>> kilo.density_fn(points, torch.zeros(10, 3)).shape
    torch.Size([10])
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..core.field_functions import RayColourFn
from ..core.scene_bounds import SceneBounds
from ..field_components.cell_networks import CellLinear, CellPacking, pack_by_cell
from ..field_components.encodings import PositionalEncoding

POSITION_FREQUENCIES, DIRECTION_FREQUENCIES, HIDDEN = 10, 4, 32  # the paper's


def cells_for_box(box: SceneBounds, longest: int = 16) -> tuple[int, int, int]:
    """Cells per axis in proportion to the box, ``longest`` along its longest side.

    Example:
        >>> cells_for_box(SceneBounds((0.0, 0.0, 0.0), (1.0, 2.0, 1.0)))
        (8, 16, 8)
    """
    extent = [hi - lo for lo, hi in zip(box.box_min, box.box_max)]
    return tuple(max(1, round(longest * e / max(extent))) for e in extent)  # type: ignore[return-value]


class KiloNerf(nn.Module):
    def __init__(self, box: SceneBounds, cells: tuple[int, int, int]) -> None:
        super().__init__()
        self.cells = tuple(cells)
        count = cells[0] * cells[1] * cells[2]
        self.register_buffer("box_min", torch.tensor(box.box_min, dtype=torch.float32))
        self.register_buffer("box_max", torch.tensor(box.box_max, dtype=torch.float32))
        self.register_buffer("_cells", torch.tensor(cells), persistent=False)
        self.position_encoding = PositionalEncoding(3, POSITION_FREQUENCIES)
        self.direction_encoding = PositionalEncoding(3, DIRECTION_FREQUENCIES)
        self.trunk = nn.ModuleList([CellLinear(count, self.position_encoding.out_dims, HIDDEN),
                                    CellLinear(count, HIDDEN, HIDDEN)])
        self.density_and_feature = CellLinear(count, HIDDEN, 1 + HIDDEN)
        self.colour_layers = nn.ModuleList([CellLinear(count, HIDDEN + self.direction_encoding.out_dims, HIDDEN),
                                            CellLinear(count, HIDDEN, 3)])

    def _cell(self, points: Tensor) -> Tensor:
        unit = (points - self.box_min) / (self.box_max - self.box_min)
        ijk = (unit * self._cells).floor().long().clamp_min(0).minimum(self._cells - 1)
        return (ijk[:, 0] * self.cells[1] + ijk[:, 1]) * self.cells[2] + ijk[:, 2]

    def _trunk(self, points: Tensor) -> tuple[Tensor, CellPacking]:
        """Density and feature ``[K, BLOCK, 1 + HIDDEN]`` in the blocked layout, and the layout."""
        packing = pack_by_cell(self._cell(points), self.trunk[0].weight.shape[0])
        unit = (points - self.box_min) / (self.box_max - self.box_min) * 2 - 1
        hidden = packing.pack(self.position_encoding(unit))
        for layer in self.trunk:
            hidden = torch.relu(layer(hidden, packing))
        return self.density_and_feature(hidden, packing), packing

    def forward(self, points: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """Density ``[P]`` and colour ``[P, 3]`` at world points seen along ``directions``."""
        trunk, packing = self._trunk(points)
        view = packing.pack(self.direction_encoding(directions))
        hidden = torch.relu(self.colour_layers[0](torch.cat([trunk[..., 1:], view], dim=-1), packing))
        colour = torch.sigmoid(self.colour_layers[1](hidden, packing))
        return nn.functional.softplus(packing.unpack(trunk[..., :1])[:, 0]), packing.unpack(colour)

    def density_fn(self, points: Tensor, directions: Tensor) -> Tensor:
        trunk, packing = self._trunk(points)
        return nn.functional.softplus(packing.unpack(trunk[..., :1])[:, 0])

    def ray_colour(self, directions: Tensor) -> RayColourFn:
        return lambda points, ray: self(points, directions.index_select(0, ray))[1]

    def flops_per_sample(self) -> dict[str, int]:
        """Multiply-adds ×2 of one sample's density, and of its colour (the trunk again)."""
        trunk = sum(layer.flops_per_sample() for layer in self.trunk) + self.density_and_feature.flops_per_sample()
        colour = trunk + sum(layer.flops_per_sample() for layer in self.colour_layers)
        return {"density": trunk, "colour": colour}
