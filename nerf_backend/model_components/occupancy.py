"""An occupancy grid over the scene's box: where the field can have density, so samples in
empty space are skipped (Instant-NGP's and nerfacc's idea).

A cell is marked occupied when the field's estimate of its largest density exceeds a
threshold. The grid field's estimate is exact (its cells are these cells, and the maximum
over a cell's corners bounds it), so with that field a cell holding density above the
threshold anywhere is never skipped; other fields give an estimate (``MarchableField``).
"""

from __future__ import annotations

import ctypes
import math
from typing import Callable

import numpy as np
import torch
from torch import Tensor, nn

from ..core.scene_bounds import SceneBounds
from ..core.tensor_keys import kept_derived
from ..kernels.build import load_kernel

# How far (in cells, on each axis) the skip grid (``OccupancyGrid.skip_cells``) spreads each
# occupied cell: a ray first checks spans of up to twice this many cells, one query each, and
# marches only the marked ones in fine steps. Wider means fewer span queries and more fine
# steps. Measured at 800×800 on 2 CPU cores (median seconds a view, three runs of `auto`):
# radius 4, 6, 8, 12: A.blend without a prior 1.07, 0.96, 0.96, 1.05; RobotExpressive without
# a prior 0.77, 0.69, 0.70, 0.78; 20_specular with Blender's prior 0.41, 0.42, 0.45, 0.51. (The
# first skip grid, 8³-cell blocks each widened by a block, marked 25 % of A.blend's cells where
# radius 4 marks 9 %.)
SKIP_RADIUS = 6


def widened(cells: Tensor, radius: int) -> Tensor:
    """Bool ``cells [X, Y, Z]`` widened by ``radius`` cells on each axis (a cube around each
    marked cell): one axis at a time, or-ing shifted copies, each round's shift as large as
    leaves no gap. At 256³ on 2 CPU cores, radius 4: 0.02 s, where max-pooling the same cube
    over floats took 0.74 s (the same cells); lego's thirty-minute grid (308 × 531 × 343
    cells, radius 6) 0.20 s a shift at a time, 0.12 s so.

    Example:
        >>> cells = torch.zeros(5, 5, 5, dtype=torch.bool)
        >>> cells[0, 2, 4] = True
        >>> widened(cells, 1)[:, 2, :].int().tolist()  # the slice through the marked cell
        [[0, 0, 0, 1, 1], [0, 0, 0, 1, 1], [0, 0, 0, 0, 0], [0, 0, 0, 0, 0], [0, 0, 0, 0, 0]]
    """
    cells, before = cells.clone(), torch.empty_like(cells)  # one scratch for every round: fresh
    for axis in range(3):  # pages for each would cost more than the or-ing (lego: 56 MB each)
        size, reach = cells.shape[axis], 0  # cells now marks each mark's ±reach along the axis
        while reach < min(radius, size - 1):
            # or-ing copies shifted ±shift reaches ±(reach + shift), without a gap while shift
            # ≤ 2·reach + 1: radius 6 in three rounds (1, 3, 2) of two passes, not six
            shift = min(2 * reach + 1, radius - reach, size - 1)
            before.copy_(cells)
            cells.narrow(axis, shift, size - shift).logical_or_(before.narrow(axis, 0, size - shift))
            cells.narrow(axis, 0, size - shift).logical_or_(before.narrow(axis, shift, size - shift))
            # Near an end the copy from beyond it is missing; the end cell's marks are the part
            # of that window inside the grid.
            cells.narrow(axis, 0, shift).logical_or_(before.narrow(axis, 0, 1))
            cells.narrow(axis, size - shift, shift).logical_or_(before.narrow(axis, size - 1, 1))
            reach += shift
    return cells


def cells_exceeding(cell_max_density: Tensor, threshold: float, allowed: Tensor | None = None) -> Tensor:
    """Bool ``[Gx, Gy, Gz]``: the cells whose largest density exceeds ``threshold`` (and,
    given ``allowed``, only those), in the grid's own layout whatever the densities' strides."""
    # Compared before combining: a field's densities may come as a transposed view, and `&`
    # over two layouts gathered byte by byte (0.8 s at 540 cells a side).
    occupied = (cell_max_density > threshold).contiguous()
    return occupied if allowed is None else occupied & allowed


def cells_over(vertex_sums: Tensor, above: float, shift: float,
               allowed: Tensor | None = None) -> tuple[Tensor, float, float] | None:
    """The cells of a grid whose vertices hold ``vertex_sums [Nz, Ny, Nx]`` (x fastest) whose
    largest corner exceeds ``above`` (and, given ``allowed [Gx, Gy, Gz]``, only those), as bool
    ``[Nx - 1, Ny - 1, Nz - 1]``; with the sums of ``max(0, v + shift)`` over the vertices and
    over the cells' largest corners (the bounds under a softplus density's mean). In one
    compiled pass (``kernels/occupied_cells.c``); None where it does not apply (not float32 on
    the CPU, fewer than two vertices an axis, no compiler): then ``cell_corner_max`` and
    ``cells_exceeding`` decide the same cells.

    Example (where a C compiler is found):
        >>> sums = torch.zeros(2, 2, 3)  # z, y, x: two cells along x
        >>> sums[0, 0, 2] = 5.0  # a corner of the second cell only
        >>> occupied, vertex_excess, cell_excess = cells_over(sums, 1.0, shift=-1.0)
        >>> occupied.flatten().tolist(), vertex_excess, cell_excess
        ([False, True], 4.0, 4.0)
    """
    if (vertex_sums.device.type != "cpu" or vertex_sums.dtype != torch.float32 or vertex_sums.dim() != 3
            or min(vertex_sums.shape) < 2):
        return None
    library = load_kernel("occupied_cells")[0]
    if library is None:
        return None
    sums = vertex_sums.detach().contiguous()
    nz, ny, nx = sums.shape
    occupied = torch.empty((nx - 1, ny - 1, nz - 1), dtype=torch.bool)
    may = None if allowed is None else allowed.to(torch.bool).contiguous()
    if may is not None and tuple(may.shape) != tuple(occupied.shape):
        raise ValueError(f"expected {tuple(occupied.shape)} allowed cells, got {tuple(may.shape)}")
    excess = (ctypes.c_double * 2)()
    library.cells_over.restype = ctypes.c_int
    failed = library.cells_over(
        ctypes.c_void_p(sums.data_ptr()), ctypes.c_int64(nz), ctypes.c_int64(ny), ctypes.c_int64(nx),
        ctypes.c_double(above), ctypes.c_float(shift), ctypes.c_void_p(None if may is None else may.data_ptr()),
        ctypes.c_void_p(occupied.data_ptr()), excess, ctypes.c_int64(torch.get_num_threads()))
    if failed:
        raise MemoryError(f"marking the cells of a {nx} × {ny} × {nz} grid found no scratch memory")
    return occupied, excess[0], excess[1]


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
    def mark(self, occupied: Tensor) -> None:
        """Mark exactly the cells set in bool ``occupied [Gx, Gy, Gz]``."""
        if tuple(occupied.shape) != self.cells:
            raise ValueError(f"expected {self.cells} cells, got {tuple(occupied.shape)}")
        self.occupied.copy_(occupied)

    def cell_index(self, points: Tensor) -> Tensor:
        """Integer cell coordinates ``[P, 3]`` of world points (clamped to the grid)."""
        unit = (points - self.box_min) / (self.box_max - self.box_min)
        return (unit * self._cells_tensor).floor().long().clamp_min(0).minimum(self._cells_tensor - 1)

    def query(self, points: Tensor) -> Tensor:
        """True where a world point lies in an occupied cell (points outside the box: False)."""
        inside = ((points >= self.box_min) & (points <= self.box_max)).all(dim=-1)
        ijk = self.cell_index(points)
        return inside & self.occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    def skip_cells(self) -> Tensor:
        """``occupied`` widened by ``SKIP_RADIUS`` cells on each axis (a cube around each
        occupied cell). So a segment no longer than ``2·SKIP_RADIUS`` cells whose midpoint lies
        in an unmarked cell holds no occupied cell: each of its points is within
        ``SKIP_RADIUS`` cells of the midpoint's cell on every axis. Cached until ``occupied``
        changes."""
        return self._derived("skip", lambda: widened(self.occupied, SKIP_RADIUS))

    def occupied_blocks(self, block: int) -> Tensor:
        """Bool ``[ceil(Gx/block), ...]``: whether each cube of ``block`` cells a side holds an
        occupied cell (small enough to stay in the caches: the compiled training march looks a
        block up before the cell, and most of a ray's steps end there). Cached until
        ``occupied`` changes.

        Example:
            >>> grid = OccupancyGrid(torch.zeros(3), torch.ones(3), cells=10)
            >>> _ = grid.occupied.zero_()
            >>> grid.occupied[9, 0, 5] = True
            >>> blocks = grid.occupied_blocks(4)
            >>> tuple(blocks.shape), blocks.nonzero().tolist()
            ((3, 3, 3), [[2, 0, 1]])
        """
        def build() -> Tensor:
            padded = [-(-n // block) * block for n in self.cells]
            cells = torch.zeros(padded, dtype=torch.bool, device=self.occupied.device)
            cells[:self.cells[0], :self.cells[1], :self.cells[2]] = self.occupied
            count = [n // block for n in padded]
            return cells.view(count[0], block, count[1], block, count[2], block).any(dim=5).any(dim=3).any(dim=1)
        return self._derived(f"blocks {block}", build)

    def occupied_block_corners(self, block: int) -> Tensor:
        """The eight corners ``[N, 8, 3]`` of each cube of ``block`` cells a side that holds an
        occupied cell (``occupied_blocks``), in the grid's frame: nothing outside them is
        marched. Cached until ``occupied`` changes.

        Example:
            >>> grid = OccupancyGrid(torch.zeros(3), torch.ones(3), cells=10)
            >>> _ = grid.occupied.zero_()
            >>> grid.occupied[9, 0, 5] = True
            >>> corners = grid.occupied_block_corners(4)
            >>> corners.amin(dim=1).mul(10).round().tolist(), corners.amax(dim=1).mul(10).round().tolist()
            ([[8.0, 0.0, 4.0]], [[10.0, 4.0, 8.0]])
        """
        def build() -> Tensor:
            side = (self.box_max - self.box_min) / self._cells_tensor * block
            low = self.box_min + self.occupied_blocks(block).nonzero().to(side.dtype) * side
            high = torch.minimum(low + side, self.box_max)
            pick = torch.tensor([[(c >> axis) & 1 for axis in range(3)] for c in range(8)], device=low.device).bool()
            return torch.where(pick, high[:, None], low[:, None])
        return self._derived(f"block corners {block}", build)

    def occupied_bricks(self) -> Tensor:
        """``occupied`` as ``brick_bits`` lays it out (8³ cells a cache line), for the compiled
        marches. Cached until ``occupied`` changes."""
        return self._derived("occupied bricks", lambda: brick_bits(self.occupied))

    def skip_bricks(self) -> Tensor:
        """``skip_cells`` as ``brick_bits`` lays it out, for the compiled render march. Cached
        until ``occupied`` changes."""
        return self._derived("skip bricks", lambda: brick_bits(self.skip_cells()))

    def _derived(self, name: str, build: Callable[[], Tensor]) -> Tensor:
        """``build()``, kept under ``name`` until ``occupied`` changes (in place, resized or
        moved): the grids the marches read are derived from it, and rebuilt only then."""
        return kept_derived(self, name, [self.occupied], build)

    def skip_span_steps(self, step: float) -> int:
        """March steps of length ``step`` in one span that ``skip_cells`` can vouch for: the
        span must be no longer than ``2·SKIP_RADIUS`` of the shortest cell side."""
        fine_side = float(((self.box_max - self.box_min) / self._cells_tensor).min())
        return max(1, math.floor(2 * SKIP_RADIUS * fine_side / step * (1 + 1e-6)))

    def occupied_along(self, origins: Tensor, directions: Tensor, t: Tensor, skip: bool = False) -> Tensor:
        """``[R, S]``: whether the points ``origins + t·directions`` (``t [R, S]``) lie in an
        occupied cell, or with ``skip`` in a marked cell of ``skip_cells`` (clamped to the
        grid). Computed in cell units along each ray (one multiply-add a point, no world
        positions), which is what the inference march queries most. Without ``skip``, points
        outside the box are unoccupied, as ``query`` has them."""
        cells = self.skip_cells() if skip else self.occupied
        side = (self.box_max - self.box_min) / self._cells_tensor
        start = (origins - self.box_min) / side
        along = directions / side
        units = torch.addcmul(start[:, None, :], along[:, None, :], t[..., None])  # [R, S, 3]
        shape = torch.tensor(cells.shape, device=units.device, dtype=units.dtype)
        inside = None if skip else ((units >= 0) & (units <= shape)).all(dim=-1)  # the box, faces included
        index = torch.minimum(units.floor_().clamp_(min=0), shape - 1).to(torch.int64)
        strides = torch.tensor([cells.shape[1] * cells.shape[2], cells.shape[2], 1], device=index.device)
        marked = cells.view(-1)[(index * strides).sum(dim=-1)]
        return marked if skip else marked & inside

    def occupied_bounds(self, margin_cells: int, min_part: float = 0.0) -> SceneBounds | None:
        """The box around the occupied cells, ``margin_cells`` wider on each side (within the
        grid's own box); None where no cell is occupied. With ``min_part``, only the pieces of
        occupied cells (touching on a face, an edge or a corner) of at least that share of the
        largest piece count: a young field's floaters are many small pieces apart from the
        scene (lego at its first growth: 211 beside the scene's, the largest 68 cells of its
        30 620), and they would keep the box as large as the scene's guess.

        Example:
            >>> grid = OccupancyGrid(torch.zeros(3), torch.ones(3), cells=10)
            >>> _ = grid.occupied.zero_()
            >>> grid.occupied[4:6, 2, 7] = True
            >>> grid.occupied[0, 9, 0] = True  # a speck, 1/2 of the largest piece
            >>> bounds = grid.occupied_bounds(1, min_part=0.6)
            >>> [round(v, 3) for v in bounds.box_min], [round(v, 3) for v in bounds.box_max]
            ([0.3, 0.1, 0.6], [0.7, 0.4, 0.9])
        """
        occupied = self.occupied.cpu().numpy()
        if min_part > 0 and occupied.any():
            from scipy import ndimage  # here: scipy.ndimage takes 0.3 s to import, a third of ours
            pieces, _ = ndimage.label(occupied, structure=np.ones((3, 3, 3)))
            sizes = np.bincount(pieces.ravel())
            sizes[0] = 0  # unoccupied
            occupied = (sizes >= min_part * sizes.max())[pieces]
        side = ((self.box_max - self.box_min) / self._cells_tensor).tolist()
        low, high = [], []
        for axis in range(3):
            others = tuple(a for a in range(3) if a != axis)
            used = np.flatnonzero(occupied.any(axis=others))
            if len(used) == 0:
                return None
            first, last = max(0, int(used[0]) - margin_cells), min(self.cells[axis], int(used[-1]) + 1 + margin_cells)
            low.append(float(self.box_min[axis]) + first * side[axis])
            high.append(float(self.box_max[axis]) if last == self.cells[axis]
                        else float(self.box_min[axis]) + last * side[axis])
        return SceneBounds(tuple(low), tuple(high))  # type: ignore[arg-type]

    @property
    def occupied_fraction(self) -> float:
        return float(self.occupied.float().mean())


BRICK = 8  # cells a side of a brick: 8³ bits, one 64-byte cache line


def brick_bits(cells: Tensor) -> Tensor:
    """A grid of bools ``[Gx, Gy, Gz]`` as bricks of 8³ cells, each brick 64 bytes (a cache
    line): uint8 ``[ceil(Gx/8), ceil(Gy/8), ceil(Gz/8), 8, 8]``, cell ``(i, j, k)`` bit ``k % 8``
    of byte ``[i/8, j/8, k/8, i % 8, j % 8]``. A ray's steps through 8 cells in any direction
    read one line; as bytes in rows along z, a ray along x read a new line (and a new page)
    each cell, and the render march waited on those reads (62 % of its time on lego's
    thirty-minute model at 255³ cells).

    Example:
        >>> cells = torch.zeros(9, 3, 10, dtype=torch.bool)
        >>> cells[8, 1, 9] = True
        >>> bricks = brick_bits(cells)
        >>> tuple(bricks.shape), bricks.nonzero().tolist(), int(bricks[1, 0, 1, 0, 1])
        ((2, 1, 2, 8, 8), [[1, 0, 1, 0, 1]], 2)
    """
    counts = [-(-n // BRICK) for n in cells.shape]
    # Packed along z first, where the cells are contiguous (numpy pads the last byte with zeros),
    # then the bytes moved into bricks: packing the bricks' bits in place took 79 ms at 255³
    # cells, this 10 (the rows alone 6). The training march reads the bricks too, and its
    # occupancy is refreshed every few dozen steps.
    rows = np.packbits(cells.cpu().numpy(), axis=2, bitorder="little")  # [Gx, Gy, Bz]
    padded = torch.zeros((counts[0] * BRICK, counts[1] * BRICK, counts[2]), dtype=torch.uint8)
    padded[:cells.shape[0], :cells.shape[1]] = torch.from_numpy(rows)
    return padded.view(counts[0], BRICK, counts[1], BRICK, counts[2]).permute(0, 2, 4, 1, 3).contiguous()
