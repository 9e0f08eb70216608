"""Factorised feature grids (TensoRF's vector-matrix decomposition), in plain PyTorch.

A feature volume ``F(x, y, z) ∈ R^C`` is stored as three planes and three lines,

    F(x, y, z) = P_xy(x, y) ⊙ L_z(z)  ⊕  P_xz(x, z) ⊙ L_y(y)  ⊕  P_yz(y, z) ⊙ L_x(x)

(⊙: per-channel product of a bilinear and a linear interpolation; ⊕: concatenation, so
``out_dims = 3 · C``). With N vertices a side that is ``3·C·(N² + N)`` parameters instead of
``C·N³``: about 3 M for C = 64, N = 128 — small enough that a dense Adam step on the CPU
costs little, which is what decides speed on the machines this project measures on. Each
axis has its own vertex count ``(Nx, Ny, Nz)``, so a flat or long box gets cubic cells
without spending vertices along its short sides.

Each component is bilinear × linear, i.e. trilinear within a grid cell, so a linear map of
the features is trilinear too and its maximum over a cell sits at one of the cell's
corners: the occupancy grid relies on this to be exact (see ``occupancy.py``).

Coordinates are normalised to [-1, 1] (``align_corners=True``: -1 and 1 are the first and
last grid vertices); a corner outside the grid reads zero (``grid_sample``'s zero padding).

Two kernels read the same grid. On the CPU each plane is read as a table of channel rows
(``[Na·Nb, C]``) by ``embedding_bag`` with the bilinear weights: one contiguous row a corner
instead of ``grid_sample``'s ``C`` reads a plane apart, 2.2x faster for rendering and 1.4x
for a training step's forward and backward (measured on captured render samples; the
bench's render column shows it). Elsewhere ``grid_sample`` stays: it is one fused kernel on
CUDA, and MPS lacks ``embedding_bag`` in some of the torch versions users have.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..core.tensor_keys import kept_derived
from .compiled_grid import channel_rows, dense_sum, read_grids

# (plane axes, line axis) of each of the three components.
_MODES = (((0, 1), 2), ((0, 2), 1), ((1, 2), 0))


Vertices = tuple[int, int, int]


class VectorMatrixGrid(nn.Module):
    """``forward(x [P, 3] in [-1, 1]) -> features [P, 3·channels]``.

    ``vertices``: grid vertices along x, y and z (an int: the same on every axis).

    Example:
        >>> grid = VectorMatrixGrid(channels=4, vertices=(16, 16, 8))
        >>> grid(torch.zeros(10, 3)).shape
        torch.Size([10, 12])
    """

    def __init__(self, channels: int, vertices: Vertices | int, init_scale: float = 0.1) -> None:
        super().__init__()
        self.channels = channels
        self.vertices: Vertices = _as_vertices(vertices)
        n = self.vertices
        self.planes = nn.ParameterList(
            [_channel_last(init_scale * torch.randn(1, channels, n[a], n[b])) for (a, b), _ in _MODES])
        self.lines = nn.ParameterList(
            [_channel_last(init_scale * torch.randn(1, channels, n[c], 1)) for _, c in _MODES])

    @property
    def out_dims(self) -> int:
        return 3 * self.channels

    def sparse_row_parameters(self) -> list[nn.Parameter]:
        """The parameters whose rows ``SparseRowAdam`` updates one by one, in the compiled
        kernel's order: plane 0, line 0, plane 1, ..."""
        return [p for pair in zip(self.planes, self.lines) for p in pair]

    def forward(self, x: Tensor) -> Tensor:
        if x.device.type == "cpu":
            compiled = read_grids([self], x)
            return compiled if compiled is not None else self._forward_rows(x)
        return self._forward_grid_sample(x)

    def _forward_rows(self, x: Tensor) -> Tensor:
        """``forward`` from channel-row tables (the CPU kernel, see the module's notes)."""
        planes, lines = self._row_tables()
        corners = [_axis_corners(x[:, axis], n) for axis, n in enumerate(self.vertices)]
        outputs = []
        for ((a, b), c), plane, line in zip(_MODES, planes, lines):
            (a_lower, a_low_weight, a_high_weight), (b_lower, b_low_weight, b_high_weight) = corners[a], corners[b]
            width = self.vertices[b]
            rows = (a_lower * width + b_lower)[:, None] + a_lower.new_tensor([0, 1, width, width + 1])
            weights = torch.stack([a_low_weight * b_low_weight, a_low_weight * b_high_weight,
                                   a_high_weight * b_low_weight, a_high_weight * b_high_weight], dim=1)
            c_lower, c_low_weight, c_high_weight = corners[c]
            line_features = F.embedding_bag(torch.stack([c_lower, c_lower + 1], dim=1), line, mode="sum",
                                            per_sample_weights=torch.stack([c_low_weight, c_high_weight], dim=1))
            plane_features = F.embedding_bag(rows, plane, per_sample_weights=weights, mode="sum")
            outputs.append(plane_features * line_features)
        return torch.cat(outputs, dim=1)

    def _row_tables(self) -> tuple[list[Tensor], list[Tensor]]:
        """Each plane as ``[Na·Nb, C]`` and each line as ``[N, C]``: views of the channel-last
        parameters. Were a parameter stored otherwise (set from outside), a copy: with
        gradients made each call, without them once per version of the weights."""
        def tables():
            return [channel_rows(p) for p in self.planes], [channel_rows(line) for line in self.lines]
        if torch.is_grad_enabled():
            return tables()
        return kept_derived(self, "tables", [*self.planes, *self.lines], tables)

    def _forward_grid_sample(self, x: Tensor) -> Tensor:
        points = x.shape[0]
        outputs = []
        for (plane_axes, line_axis), plane, line in zip(_MODES, self.planes, self.lines):
            # grid_sample's grid is (width coord, height coord): plane[h = axis a, w = axis b].
            # Columns stacked, not x[:, [b, a]]: a Python list index is copied to the GPU on
            # every call, and that copy waits for the GPU (a step reads the grids 3 times).
            plane_grid = torch.stack([x[:, plane_axes[1]], x[:, plane_axes[0]]], dim=-1).view(1, points, 1, 2)
            line_grid = torch.stack([torch.zeros_like(x[:, line_axis]), x[:, line_axis]], dim=-1).view(1, points, 1, 2)
            plane_feat = F.grid_sample(plane, plane_grid, mode="bilinear", align_corners=True)
            line_feat = F.grid_sample(line, line_grid, mode="bilinear", align_corners=True)
            outputs.append((plane_feat * line_feat).view(self.channels, points))
        return torch.cat(outputs, dim=0).T

    @torch.no_grad()
    def resize(self, vertices: Vertices | int, lower: tuple[float, float, float] = (-1.0, -1.0, -1.0),
               upper: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> None:
        """Resample every plane and line to ``vertices`` spread from ``lower`` to ``upper`` (in
        this grid's [-1, 1] coordinates): the whole grid by default (coarse-to-fine training),
        or a part of it (the box fitted to the scene), which then becomes [-1, 1]. A factor
        restricted to a sub-range is still a factor, so the represented volume is unchanged
        there up to interpolation."""
        n = self.vertices = _as_vertices(vertices)
        positions = [torch.linspace(lo, hi, count, dtype=torch.float64) for lo, hi, count in zip(lower, upper, n)]
        # New Parameter objects (not .data swaps): autograd keeps each parameter's shape.
        for i, ((a, b), c) in enumerate(_MODES):
            self.planes[i] = _channel_last(_resampled(self.planes[i], positions[a], positions[b]))
            self.lines[i] = _channel_last(_resampled(self.lines[i], positions[c], None))

    @torch.no_grad()
    def dense_sum(self) -> Tensor:
        """The sum of all features at the grid's vertices, ``[Nz, Ny, Nx]`` (z, y, x: the
        layout ``grid_sample`` reads volumes in), without holding every channel's volume:
        each mode is one matrix product of ``C``-long rows, accumulated in place, so a 256³
        grid needs 64 MB, not gigabytes, and no volume-sized copy is made. Always float32:
        under autocast the first product would come out in half precision and the in-place
        sums could not take it."""
        compiled = dense_sum(self)  # one pass writing each vertex once, where it applies
        if compiled is not None:
            return compiled
        with torch.autocast(self.planes[0].device.type, enabled=False):
            return self._dense_sum_float32()

    def _dense_sum_float32(self) -> Tensor:
        (nx, ny, nz), channels = self.vertices, self.channels
        (xy, xz, yz), (z_line, y_line, x_line) = [p[0] for p in self.planes], [l[0, :, :, 0] for l in self.lines]
        # (y, z) plane × x line: V[z, y, x] = Σ_c P[c, y, z] L[c, x]
        volume = (yz.permute(2, 1, 0).reshape(nz * ny, channels) @ x_line).view(nz, ny, nx)
        # (x, y) plane × z line: V[z, (y, x)] += Σ_c L[c, z] P[c, x, y]
        volume.view(nz, ny * nx).addmm_(z_line.T, xy.transpose(1, 2).reshape(channels, ny * nx))
        # (x, z) plane × y line: V[z, y, x] += Σ_c L[c, y] P[c, x, z], one product per z
        volume.baddbmm_(y_line.T.expand(nz, ny, channels), xz.permute(2, 0, 1))
        return volume


def _axis_corners(coordinate: Tensor, vertices: int) -> tuple[Tensor, Tensor, Tensor]:
    """The lower of the two vertices read around each ``coordinate [P]`` in [-1, 1] on an
    axis of ``vertices`` (kept inside the grid, so both exist) and the weights of the two: the
    hat function ``max(0, 1 - |position - vertex|)``, which is linear interpolation inside the
    grid and fades to 0 within a cell outside it, as ``grid_sample``'s zero padding reads it."""
    position = (coordinate + 1.0) * (0.5 * (vertices - 1))
    lower = position.detach().floor().clamp(0, vertices - 2)
    from_lower = position - lower
    return lower.long(), (1.0 - from_lower.abs()).clamp_min(0.0), (1.0 - (from_lower - 1.0).abs()).clamp_min(0.0)


def _resampled(factor: Tensor, rows: Tensor, columns: Tensor | None) -> Tensor:
    """A plane ``[1, C, H, W]`` read bilinearly at ``rows [h] × columns [w]`` (a line ``[1, C, H, 1]``
    at ``rows`` only), in its [-1, 1] coordinates (``align_corners``: ±1 are its end vertices)."""
    columns = torch.zeros(1, dtype=rows.dtype) if columns is None else columns
    where = torch.stack(torch.meshgrid(columns, rows, indexing="xy"), dim=-1)  # [h, w, (column, row)]
    where = where.to(device=factor.device, dtype=factor.dtype)[None]
    return F.grid_sample(factor, where, mode="bilinear", align_corners=True)


def _channel_last(values: Tensor) -> nn.Parameter:
    """A plane ``[1, C, Na, Nb]`` or line ``[1, C, N, 1]`` stored channel-last (a vertex's C
    channels contiguous): the shape PyTorch's ops expect, the layout the row reads want."""
    return nn.Parameter(values.detach().contiguous(memory_format=torch.channels_last))


def _as_vertices(vertices: Vertices | int) -> Vertices:
    if isinstance(vertices, int):
        return (vertices, vertices, vertices)
    if len(vertices) != 3 or min(vertices) < 2:
        raise ValueError(f"a grid needs at least 2 vertices on each of 3 axes, got {vertices}")
    return (int(vertices[0]), int(vertices[1]), int(vertices[2]))
