"""A sparse voxel grid (Plenoxels'): values at the vertices of a regular grid, read trilinearly,
with the vertices of empty space pruned.

A dense table of links ``[Nx, Ny, Nz]`` (int32) gives each vertex its row of ``values``
``[rows, channels]``, or -1 for a pruned vertex, which reads as zeros. A sample's features are
the trilinear blend of its cell's 8 corner rows. Only kept vertices cost memory and optimiser
work: at 256³ vertices, 28 channels held densely would be 1.9 GB (before Adam's moments);
pruned to the cells a scene fills it is a few percent of that.

Rows are padded to a multiple of 8 channels (``CHANNEL_BLOCK``): the compiled kernel reads a
row in whole vectors and cache lines.

Two kernels read the same grid: on the CPU in float32, with a C compiler, the compiled one
(``kernels/sparse_grid.c``: one pass over the samples, the gradient added only into the rows
they touched and marked for ``SparseRowAdam``), elsewhere PyTorch's gathers (CUDA, MPS, no
compiler). tests/test_sparse_grid.py checks both and their gradients against each other.

Example:
    >>> grid = SparseVoxelGrid(channels=4, vertices=(5, 5, 5))
    >>> with torch.no_grad():
    ...     _ = grid.values.fill_(1.0)
    >>> grid(torch.zeros(3, 3)).tolist()[0]  # every channel of every corner is 1
    [1.0, 1.0, 1.0, 1.0]
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor, nn

from ..kernels.build import kernel_or_note

CHANNEL_BLOCK = 8  # sparse_grid.c's BLOCK
CORNERS = 8
# Points read at a time while resampling the grid onto new vertices.
RESAMPLE_CHUNK = 1 << 18

Vertices = tuple[int, int, int]


class _Grid(ctypes.Structure):
    _fields_ = [("links", ctypes.c_void_p), ("values", ctypes.c_void_p), ("n", ctypes.c_int64 * 3),
                ("channels", ctypes.c_int64)]


def sparse_grid_library() -> ctypes.CDLL | None:
    """The built kernel, or None (why is said once on stderr: the grid then reads through PyTorch)."""
    library, _ = kernel_or_note("sparse_grid", "reading the sparse voxel grid through PyTorch")
    if library is not None:
        library.sparse_forward.restype = ctypes.c_int
        library.sparse_backward.restype = ctypes.c_int
    return library


def padded_channels(channels: int) -> int:
    return -(-channels // CHANNEL_BLOCK) * CHANNEL_BLOCK


class SparseVoxelGrid(nn.Module):
    """``forward(x [P, 3] in [-1, 1]) -> features [P, channels]``, trilinear over the kept
    vertices (``align_corners``: -1 and 1 are the first and last vertices; outside the grid a
    corner reads zero). ``keep`` (bool ``[Nx, Ny, Nz]``): the vertices to hold (all: None)."""

    def __init__(self, channels: int, vertices: Vertices, keep: Tensor | None = None) -> None:
        super().__init__()
        self.channels = channels
        self.vertices: Vertices = tuple(vertices)  # type: ignore[assignment]
        if keep is None:
            keep = torch.ones(self.vertices, dtype=torch.bool)
        links, rows = _links_of(keep)
        self.register_buffer("links", links)
        self.values = nn.Parameter(torch.zeros(rows, padded_channels(channels)))

    @property
    def rows(self) -> int:
        return self.values.shape[0]

    def forward(self, x: Tensor) -> Tensor:
        """The features at ``x`` (``channels`` of them; the padding is dropped)."""
        if _compiled_applies(self, x):
            return _ReadSparse.apply(x, self, self.values)[:, :self.channels]
        rows, weights = self._corners(x)
        blended = (self.values[:, :self.channels].index_select(0, rows.reshape(-1)).view(*rows.shape, self.channels)
                   * weights[..., None]).sum(dim=1)
        return blended

    @torch.no_grad()
    def channel(self, x: Tensor, channel: int = 0) -> Tensor:
        """One channel at ``x [P]``, without gradients (the density the march reads)."""
        if _compiled_applies(self, x):
            out = torch.empty(x.shape[0])
            if x.shape[0]:
                library = sparse_grid_library()
                grid = self.kernel_view(channel)
                _check(library.sparse_forward(ctypes.byref(grid), _pointer(x.contiguous()), ctypes.c_int64(x.shape[0]),
                                              None, _pointer(out), None, None, ctypes.c_int64(torch.get_num_threads())))
            return out
        rows, weights = self._corners(x)
        return (self.values[:, channel].index_select(0, rows.reshape(-1)).view(rows.shape) * weights).sum(dim=1)

    def kernel_view(self, first_channel: int = 0) -> _Grid:
        """The grid as ``sparse_grid.c`` reads it (from ``first_channel``: the density channel
        is read as the row's first); keep the grid alive while it is read."""
        grid = _Grid()
        grid.links = self.links.data_ptr()
        grid.values = self.values.data_ptr() + 4 * first_channel
        grid.n = (ctypes.c_int64 * 3)(*self.vertices)
        grid.channels = self.values.shape[1]
        return grid

    def _corners(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Each point's 8 corner rows ``[P, 8]`` (a pruned corner: row 0, weight 0) and weights."""
        n = torch.tensor(self.vertices, device=x.device)
        position = (x.float() + 1.0) * 0.5 * (n - 1)
        lower = position.floor().nan_to_num(0.0).clamp(min=torch.zeros_like(n), max=n - 2)
        from_lower = position - lower
        low = (1.0 - from_lower.abs()).clamp_min(0.0).nan_to_num(0.0)
        high = (1.0 - (from_lower - 1.0).abs()).clamp_min(0.0).nan_to_num(0.0)
        lower = lower.long()
        offsets = torch.tensor([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(CORNERS)], device=x.device)
        corner = lower[:, None, :] + offsets  # [P, 8, 3]
        flat = (corner[..., 0] * n[1] + corner[..., 1]) * n[2] + corner[..., 2]
        rows = self.links.view(-1)[flat].long()
        axis_weights = torch.where(offsets.bool(), high[:, None, :], low[:, None, :])
        weights = axis_weights.prod(dim=-1) * (rows >= 0)
        return rows.clamp_min(0), weights

    def sparse_row_parameters(self) -> list[nn.Parameter]:
        """The parameters whose rows ``SparseRowAdam`` updates one by one."""
        return [self.values]

    @torch.no_grad()
    def dense(self, channel: int = 0) -> Tensor:
        """One channel at every vertex ``[Nx, Ny, Nz]`` (zero where pruned)."""
        values = self.values[:, channel]
        kept = self.links >= 0
        out = torch.zeros(self.vertices, dtype=values.dtype, device=values.device)
        out[kept] = values[self.links[kept].long()]
        return out

    @torch.no_grad()
    def resampled(self, vertices: Vertices, low: tuple[float, float, float], high: tuple[float, float, float],
                  keep: Tensor) -> "SparseVoxelGrid":
        """A new grid of ``vertices`` over the part ``[low, high]`` of this one (normalised
        coordinates), holding the vertices ``keep`` marks (bool ``[vertices]``), each valued
        by a trilinear read of this grid there."""
        grid = SparseVoxelGrid(self.channels, vertices, keep.cpu()).to(self.values.device)
        kept = keep.nonzero()
        lo, hi = torch.tensor(low, device=kept.device), torch.tensor(high, device=kept.device)
        spacing = (hi - lo) / (torch.tensor(vertices, device=kept.device) - 1)
        for first in range(0, kept.shape[0], RESAMPLE_CHUNK):
            points = lo + kept[first:first + RESAMPLE_CHUNK].float() * spacing
            grid.values[first:first + points.shape[0], :self.channels] = self(points.to(self.values.device))
        return grid

    def take(self, other: "SparseVoxelGrid") -> None:
        """Become ``other`` (its vertices, links and values: new parameters)."""
        self.vertices = other.vertices
        self.links = other.links
        self.values = nn.Parameter(other.values.detach())

    def take_shapes(self, links_shape: Vertices, rows: int) -> None:
        """Empty buffers of a checkpoint's shapes, for ``load_state_dict`` to fill."""
        self.vertices = tuple(links_shape)  # type: ignore[assignment]
        self.links = torch.full(links_shape, -1, dtype=torch.int32, device=self.links.device)
        self.values = nn.Parameter(torch.zeros(rows, self.values.shape[1], device=self.values.device))


def _links_of(keep: Tensor) -> tuple[Tensor, int]:
    """Links numbering the kept vertices in order (-1 elsewhere) and their count."""
    links = torch.full(keep.shape, -1, dtype=torch.int32)
    rows = int(keep.sum())
    links[keep] = torch.arange(rows, dtype=torch.int32)
    return links, rows


def _pointer(tensor: Tensor | None) -> ctypes.c_void_p | None:
    return None if tensor is None else ctypes.c_void_p(tensor.data_ptr())


def _check(status: int) -> None:
    if status != 0:  # _compiled_applies keeps every call within the kernel's limits
        raise RuntimeError(f"sparse_grid.c refused the call (status {status})")


def _compiled_applies(grid: SparseVoxelGrid, x: Tensor) -> bool:
    return (x.device.type == "cpu" and x.dtype == torch.float32 and not x.requires_grad
            and grid.values.dtype == torch.float32 and grid.values.device.type == "cpu"
            and min(grid.vertices) >= 2 and sparse_grid_library() is not None)


def _gradient_sink(grid: SparseVoxelGrid):
    """The grid's row-gradient buffers where ``SparseRowAdam`` gave it some for its current
    values, else None (dense gradients through autograd)."""
    sink = getattr(grid, "row_gradients", None)
    return sink if sink is not None and sink.serves([grid.values]) else None


class _ReadSparse(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, grid: SparseVoxelGrid, values: Tensor) -> Tensor:
        x = x.contiguous()
        points = x.shape[0]
        features = values.new_empty((points, values.shape[1]))
        rows = torch.empty((points, CORNERS), dtype=torch.int32)
        weights = torch.empty((points, CORNERS))
        if points:
            view = grid.kernel_view()
            _check(sparse_grid_library().sparse_forward(
                ctypes.byref(view), _pointer(x), ctypes.c_int64(points), _pointer(features), None, _pointer(rows),
                _pointer(weights), ctypes.c_int64(torch.get_num_threads())))
        ctx.grid = grid
        ctx.save_for_backward(rows, weights, values)
        return features

    @staticmethod
    def backward(ctx, grad_features: Tensor):
        rows, weights, values = ctx.saved_tensors
        grid = ctx.grid
        sink = _gradient_sink(grid)
        if sink is not None:
            into, marks, returned = sink.gradients[0], sink.marks[0], None
        else:
            into, marks = torch.zeros_like(values), None
            returned = into
        if rows.shape[0]:
            view = grid.kernel_view()
            _check(sparse_grid_library().sparse_backward(
                ctypes.byref(view), _pointer(rows), _pointer(weights), ctypes.c_int64(rows.shape[0]),
                _pointer(grad_features.float().contiguous()), _pointer(into), _pointer(marks),
                ctypes.c_int64(torch.get_num_threads())))
        return None, None, returned
