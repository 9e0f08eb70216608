"""Many tiny networks, one per cell of a grid over the scene (KiloNeRF's), evaluated together:
the samples are sorted by cell and cut into blocks of ``BLOCK`` rows that each belong to one
cell, so every layer is one batched matrix product over the blocks with each block's own
weights (a grouped GEMM in plain PyTorch, on any device). A cell's last block is padded: at
most ``BLOCK - 1`` wasted rows a cell.

Example:
    >>> layer = CellLinear(cells=4, inputs=3, outputs=2)
    >>> packing = pack_by_cell(torch.tensor([2, 0, 2, 1]), cells=4)
    >>> out = packing.unpack(layer(packing.pack(torch.ones(4, 3)), packing))
    >>> out.shape
    torch.Size([4, 2])
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

# Rows a block: large enough that a product's weights are read once for many rows, small
# enough that a cell's padding stays a small share where cells hold a few hundred samples.
BLOCK = 64


@dataclass(frozen=True)
class CellPacking:
    """Where each sample sits in the blocked layout: ``slot [P]`` (block · BLOCK + row) and
    each block's cell ``block_cell [K]``."""

    slot: Tensor
    block_cell: Tensor
    rows: int  # K · BLOCK

    def pack(self, values: Tensor) -> Tensor:
        """``[P, C]`` → ``[K, BLOCK, C]`` (padding rows zero)."""
        blocked = values.new_zeros((self.rows, values.shape[1]))
        blocked.index_copy_(0, self.slot, values)
        return blocked.view(-1, BLOCK, values.shape[1])

    def unpack(self, blocked: Tensor) -> Tensor:
        """``[K, BLOCK, C]`` → ``[P, C]`` in the samples' own order."""
        return blocked.reshape(self.rows, blocked.shape[-1]).index_select(0, self.slot)


def pack_by_cell(cell: Tensor, cells: int) -> CellPacking:
    """The blocked layout of samples whose cells are ``cell [P]`` (values in ``[0, cells)``)."""
    counts = torch.bincount(cell, minlength=cells)
    blocks = (counts + BLOCK - 1) // BLOCK
    first_block = torch.cumsum(blocks, 0) - blocks
    order = torch.argsort(cell, stable=True)
    sorted_cell = cell.index_select(0, order)
    first_sample = torch.cumsum(counts, 0) - counts
    rank = torch.arange(cell.numel(), device=cell.device) - first_sample.index_select(0, sorted_cell)
    slot_sorted = first_block.index_select(0, sorted_cell) * BLOCK + rank
    slot = torch.empty_like(slot_sorted).index_copy_(0, order, slot_sorted)
    block_cell = torch.repeat_interleave(torch.arange(cells, device=cell.device), blocks)
    return CellPacking(slot, block_cell, int(blocks.sum()) * BLOCK)


class CellLinear(nn.Module):
    """A linear layer per cell: ``weight [cells, inputs, outputs]``, ``bias [cells, outputs]``,
    each initialised as ``nn.Linear``'s."""

    def __init__(self, cells: int, inputs: int, outputs: int) -> None:
        super().__init__()
        bound = 1.0 / math.sqrt(inputs)
        self.weight = nn.Parameter(torch.empty(cells, inputs, outputs).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(cells, outputs).uniform_(-bound, bound))

    def forward(self, blocked: Tensor, packing: CellPacking) -> Tensor:
        """``[K, BLOCK, inputs]`` → ``[K, BLOCK, outputs]``, each block through its cell's layer."""
        weight = self.weight.index_select(0, packing.block_cell)
        bias = self.bias.index_select(0, packing.block_cell).unsqueeze(1)
        return torch.baddbmm(bias, blocked, weight)

    def flops_per_sample(self) -> int:
        return 2 * self.weight.shape[1] * self.weight.shape[2]
