"""Voxelise triangles into a conservative occupancy grid: the maths of the occupancy prior.

Every cell that a triangle passes through must end up marked (the NeRF backend skips the
cells that are not, so a missed cell is a hole in the model).  Exact triangle/box tests per
cell would be slow in numpy; instead each triangle is sampled on a barycentric sub-grid so
fine that every point of the triangle lies closer than one cell size to a sample, the cells
of the samples are marked, and the marks are dilated by one cell (3x3x3): any cell the
triangle touches holds a triangle point, whose nearest sample lies in the same or a
neighbouring cell on every axis.  The margin then dilates further.  `solid` adds every cell
the marked shell encloses (not reachable from the grid's border through unmarked cells).

numpy only, no bpy: tested as plain maths (tests/test_occupancy_prior.py).  The Blender side
(which triangles, which margins) is scene_occupancy.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np

#: Cells of extra margin everywhere: the backend's own grid is coarser and its surface fuzzy.
BASE_MARGIN_CELLS = 1
#: Cells across the longest axis of the grid.
DEFAULT_RESOLUTION = 256
#: Samples marked per chunk (bounds the memory of one vectorised step to ~100 MB).
_CHUNK_SAMPLES = 2_000_000
RULE = "every cell a renderable triangle passes through is marked, then dilated by the margin"


@dataclass
class Part:
    """Geometry sharing one margin, in the NeRF frame.

    `triangles` [T, 3, 3] (triangle, corner, xyz); `boxes` [B, 2, 3] (box, min/max, xyz) are
    filled whole; `margin` (NeRF units, >= 0) is added on top of the base margin; `region`
    is what its surface is made of, an index into `APPEARANCE_REGIONS` (0: not classified).

    >>> Part(np.zeros((0, 3, 3)), margin=0.1).margin
    0.1
    """

    triangles: np.ndarray
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    margin: float = 0.0
    region: int = 0

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(low, high) of its triangles and boxes grown by its margin, or None when empty.

        >>> low, high = Part(np.array([[[0, 0, 0], [1, 0, 0], [0, 2, 0]]], float), margin=0.5).bounds()
        >>> low.tolist(), high.tolist()
        ([-0.5, -0.5, -0.5], [1.5, 2.5, 0.5])
        """
        points = np.concatenate([self.triangles.reshape(-1, 3), self.boxes.reshape(-1, 3)])
        if len(points) == 0:
            return None
        return points.min(axis=0) - self.margin, points.max(axis=0) + self.margin


@dataclass
class Grid:
    """Cubic cells of side `cell_size`; cell (i, j, k) spans box_min + cell_size * [(i, j, k), (i+1, j+1, k+1)].

    >>> grid = Grid(np.zeros(3), 0.5, (4, 2, 2))
    >>> grid.box_max.tolist()
    [2.0, 1.0, 1.0]
    """

    box_min: np.ndarray
    cell_size: float
    shape: tuple[int, int, int]

    @property
    def box_max(self) -> np.ndarray:
        return self.box_min + self.cell_size * np.asarray(self.shape, dtype=np.float64)

    def cell_of(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] int indices of the cells holding `points` (clipped into the grid).

        >>> Grid(np.zeros(3), 0.5, (4, 2, 2)).cell_of(np.array([[0.6, 0.1, 0.99]])).tolist()
        [[1, 0, 1]]
        """
        cells = np.floor((points - self.box_min) / self.cell_size).astype(np.int64)
        return np.clip(cells, 0, np.asarray(self.shape) - 1)


def choose_grid(low: np.ndarray, high: np.ndarray, resolution: int, padding_cells: int) -> Grid:
    """The grid over [low, high] grown by `padding_cells` cells, `resolution` cells on its longest axis.

    The box is centred on the bounds; shorter axes get as many cells as they need.

    >>> grid = choose_grid(np.zeros(3), np.array([2.0, 1.0, 0.0]), 24, 2)
    >>> grid.shape, grid.cell_size
    ((24, 14, 4), 0.1)
    """
    if resolution <= 2 * padding_cells:
        raise ValueError(f"resolution {resolution} leaves no cells inside a padding of {padding_cells}")
    extent = np.asarray(high, np.float64) - np.asarray(low, np.float64)
    longest = float(extent.max())
    if not (longest > 0.0 and math.isfinite(longest)):
        raise ValueError(f"the geometry has no extent ({longest})")
    cell_size = longest / (resolution - 2 * padding_cells)
    # The relative slack keeps the longest axis at exactly `resolution` despite float rounding.
    inner = np.ceil(extent / cell_size * (1.0 - 1e-12)).astype(np.int64)
    shape = tuple(int(min(n + 2 * padding_cells, resolution)) for n in inner)
    centre = (np.asarray(low, np.float64) + np.asarray(high, np.float64)) / 2.0
    box_min = centre - cell_size * np.asarray(shape, np.float64) / 2.0
    return Grid(box_min, cell_size, shape)  # type: ignore[arg-type]


def subdivisions(triangles: np.ndarray, cell_size: float) -> np.ndarray:
    """[T] int: n per triangle so that n x n sub-triangles have every edge shorter than `cell_size`.

    n = floor(longest edge / cell_size) + 1 (not ceil: an edge exactly one cell long must still
    be split, so every triangle point lies strictly closer than a cell to a sample).

    >>> subdivisions(np.array([[[0, 0, 0], [1, 0, 0], [0, 0.5, 0]]], float), 0.5).tolist()
    [3]
    """
    edges = triangles - np.roll(triangles, 1, axis=1)
    longest = np.sqrt((edges ** 2).sum(axis=2)).max(axis=1)
    return np.floor(longest / cell_size).astype(np.int64) + 1


def barycentric_grid(n: int) -> np.ndarray:
    """[(n+1)(n+2)/2, 3] weights: the corners of the n x n sub-triangles of a triangle.

    Each sub-triangle is the triangle scaled by 1/n, so a point inside one is within its
    longest edge (edge / n) of each of its corners.

    >>> barycentric_grid(1).tolist()
    [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]
    """
    a, b = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = a + b <= n
    u, v = a[keep] / n, b[keep] / n
    return np.stack([1.0 - u - v, u, v], axis=1)


def mark_triangles(marked: np.ndarray, grid: Grid, triangles: np.ndarray) -> None:
    """Mark (in place) the cells of the sub-grid samples of `triangles` (not dilated yet).

    >>> marked = np.zeros((4, 4, 4), bool)
    >>> mark_triangles(marked, Grid(np.zeros(3), 1.0, (4, 4, 4)), np.array([[[0.5, 0.5, 0.5], [2.5, 0.5, 0.5], [0.5, 0.5, 0.5]]]))
    >>> np.argwhere(marked).tolist()
    [[0, 0, 0], [1, 0, 0], [2, 0, 0]]
    """
    triangles = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    if len(triangles) == 0:
        return
    counts = subdivisions(triangles, grid.cell_size)
    for n in np.unique(counts):
        weights = barycentric_grid(int(n))
        group = triangles[counts == n]
        step = max(1, _CHUNK_SAMPLES // len(weights))
        for start in range(0, len(group), step):
            samples = np.einsum("kv,tvc->tkc", weights, group[start:start + step]).reshape(-1, 3)
            cells = grid.cell_of(samples)
            marked[cells[:, 0], cells[:, 1], cells[:, 2]] = True


def mark_boxes(marked: np.ndarray, grid: Grid, boxes: np.ndarray) -> None:
    """Mark (in place) every cell that a box [B, 2, 3] overlaps or touches.

    >>> marked = np.zeros((4, 4, 4), bool)
    >>> mark_boxes(marked, Grid(np.zeros(3), 1.0, (4, 4, 4)), np.array([[[0.5, 0.5, 0.5], [1.5, 0.9, 0.9]]]))
    >>> np.argwhere(marked).tolist()
    [[0, 0, 0], [1, 0, 0]]
    """
    for low, high in np.asarray(boxes, np.float64).reshape(-1, 2, 3):
        first, last = grid.cell_of(low[None])[0], grid.cell_of(high[None])[0]
        marked[first[0]:last[0] + 1, first[1]:last[1] + 1, first[2]:last[2] + 1] = True


def dilate(marked: np.ndarray, cells: int) -> np.ndarray:
    """`marked` grown by `cells` cells on every axis (a (2 cells + 1)^3 cube), clipped to the grid.

    A cube is the product of three segments, so it dilates axis by axis; each axis doubles the
    reach per step (log2(cells) shifts).

    >>> grown = dilate(np.pad(np.ones((1, 1, 1), bool), 3), 2)
    >>> int(grown.sum()), np.argwhere(grown).min(axis=0).tolist()
    (125, [1, 1, 1])
    """
    result = marked.copy()
    for axis in range(3):
        reach = 0
        while reach < cells:
            step = min(reach + 1, cells - reach)
            shifted = result.copy()
            _or_shifted(shifted, result, axis, step)
            _or_shifted(shifted, result, axis, -step)
            result, reach = shifted, reach + step
    return result


def _or_shifted(target: np.ndarray, source: np.ndarray, axis: int, shift: int) -> None:
    """target |= source moved by `shift` cells along `axis` (what leaves the grid is dropped).

    >>> target = np.zeros((4, 1, 1), bool); source = np.array([1, 0, 0, 1], bool).reshape(4, 1, 1)
    >>> _or_shifted(target, source, 0, 1); target.ravel().tolist()
    [False, True, False, False]
    """
    length = source.shape[axis]
    if abs(shift) >= length:
        return
    to = [slice(None)] * 3
    from_ = [slice(None)] * 3
    to[axis] = slice(shift, None) if shift > 0 else slice(None, length + shift)
    from_[axis] = slice(None, length - shift) if shift > 0 else slice(-shift, None)
    target[tuple(to)] |= source[tuple(from_)]


def outside(surface: np.ndarray) -> np.ndarray:
    """Cells not in `surface` reachable from outside the grid through 6-connected unmarked cells.

    Scan-line flood fill: a sweep along an axis spreads reach through whole runs of unmarked
    cells at once; sweeps cycle through the axes until three in a row change nothing (as many
    sweeps as the longest path needs turns, not cells).

    >>> shell = np.ones((5, 5, 5), bool); shell[2, 2, 2] = False
    >>> int(outside(np.pad(shell, 1)).sum())  # the padding layer only, not the enclosed centre
    218
    """
    empty = ~surface
    reach = np.zeros_like(surface)
    for axis in range(3):
        for end in (0, -1):
            index: list = [slice(None)] * 3
            index[axis] = end
            reach[tuple(index)] = empty[tuple(index)]
    count, unchanged, axis = int(reach.sum()), 0, 0
    while unchanged < 3:
        reach = _sweep(reach, empty, axis)
        # After a change, the axis just swept is settled: the other two remain to be checked.
        unchanged = unchanged + 1 if int(reach.sum()) == count else 1
        count, axis = int(reach.sum()), (axis + 1) % 3
    return reach


def _sweep(reach: np.ndarray, empty: np.ndarray, axis: int) -> np.ndarray:
    """Spread `reach` along `axis` through every run of empty cells that holds a reached cell.

    `run` numbers the runs along each line (barriers counted so far, never decreasing), so a
    cell's run holds a reached cell at or before it when the running maximum of the reached
    cells' run numbers equals its own, and at or after it likewise with a reversed minimum.

    >>> empty = np.array([1, 1, 0, 1, 1, 1], bool).reshape(1, 1, 6)
    >>> reach = np.array([0, 0, 0, 0, 1, 0], bool).reshape(1, 1, 6)
    >>> _sweep(reach, empty, 2).ravel().astype(int).tolist()
    [0, 0, 0, 1, 1, 1]
    """
    dtype = np.int16 if max(reach.shape) < 32000 else np.int32  # half the memory traffic of int32
    run = np.cumsum(~empty, axis=axis, dtype=dtype)
    forward = np.maximum.accumulate(np.where(reach, run, dtype(-1)), axis=axis) == run
    reversed_tags = np.flip(np.where(reach, run, np.iinfo(dtype).max), axis)
    backward = np.flip(np.minimum.accumulate(reversed_tags, axis=axis), axis) == run
    return empty & (forward | backward)


@dataclass
class Occupancy:
    """The prior: `surface` (marked cells, dilated) and `solid` (plus what they enclose), and
    `regions` (uint8): the appearance region of the surface in each surface cell, the largest
    index of the parts that mark it (0 elsewhere)."""

    grid: Grid
    surface: np.ndarray
    solid: np.ndarray
    regions: np.ndarray

    def arrays(self) -> dict[str, np.ndarray]:
        """The npz content: surface, solid, regions, box_min, box_max, cell_size.

        >>> sorted(voxelise([Part(np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 1]]], float))], 32).arrays())
        ['box_max', 'box_min', 'cell_size', 'regions', 'solid', 'surface']
        """
        return {"surface": self.surface, "solid": self.solid, "regions": self.regions,
                "box_min": self.grid.box_min, "box_max": self.grid.box_max, "cell_size": np.float64(self.grid.cell_size)}


def margin_in_cells(margin: float, cell_size: float) -> int:
    """A margin in NeRF units as whole cells, rounded up.

    >>> margin_in_cells(0.25, 0.1), margin_in_cells(0.0, 0.1)
    (3, 0)
    """
    return int(math.ceil(margin / cell_size))


def voxelise(parts: Sequence[Part], resolution: int = DEFAULT_RESOLUTION,
             base_margin_cells: int = BASE_MARGIN_CELLS) -> Occupancy:
    """The occupancy prior of `parts`: each part's cells dilated by 1 + base margin + its own margin.

    The grid spans the parts' bounds (grown by their margins) plus room for the dilation and an
    empty outer layer, so nothing marked touches the border and outside the box is empty.
    Raises ValueError when there is no geometry or it has no extent.

    >>> cube = Part(np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 0, 1], [0, 1, 1]]], float))
    >>> prior = voxelise([cube], 32)
    >>> prior.grid.shape, bool(prior.surface[0].any()), bool(prior.solid[16, 16, 16])
    ((32, 32, 32), False, False)
    """
    bounds = [part.bounds() for part in parts]
    present = [b for b in bounds if b is not None]
    if not present:
        raise ValueError("there is no renderable geometry to voxelise")
    low = np.min([b[0] for b in present], axis=0)
    high = np.max([b[1] for b in present], axis=0)
    # Dilation (1 + base), one more for rounding a part's margin up to cells, one empty layer
    # for the flood fill, one for floor() at the high end.
    grid = choose_grid(low, high, resolution, base_margin_cells + 4)
    by_margin: dict[tuple[int, int], np.ndarray] = {}  # (cells of dilation, region) -> marks
    for part in parts:
        cells = 1 + base_margin_cells + margin_in_cells(part.margin, grid.cell_size)
        marked = by_margin.setdefault((cells, part.region), np.zeros(grid.shape, bool))
        mark_triangles(marked, grid, part.triangles)
        mark_boxes(marked, grid, part.boxes)
    surface = np.zeros(grid.shape, bool)
    regions = np.zeros(grid.shape, np.uint8)
    for (cells, region), marked in by_margin.items():
        grown = dilate(marked, cells)
        surface |= grown
        np.maximum(regions, np.where(grown, np.uint8(region), np.uint8(0)), out=regions)
    return Occupancy(grid, surface, ~outside(surface), regions)


def box_triangles(low: Iterable[float], high: Iterable[float]) -> np.ndarray:
    """[12, 3, 3] triangles of the closed axis-aligned box [low, high] (for tests and examples).

    >>> box_triangles([0, 0, 0], [1, 1, 1]).shape
    (12, 3, 3)
    """
    low, high = np.asarray(list(low), np.float64), np.asarray(list(high), np.float64)
    corners = np.array([[(high if (i >> axis) & 1 else low)[axis] for axis in range(3)] for i in range(8)])
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return np.array([corners[[a, b, c]] for a, b, c, d in faces] + [corners[[a, c, d]] for a, b, c, d in faces])
