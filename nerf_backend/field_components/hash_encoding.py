"""Multiresolution hash encoding (Müller et al. 2022, Instant-NGP), in plain PyTorch so it
runs wherever PyTorch does (CPU, CUDA, MPS) with no compiled extension.

``levels`` grids from ``base_resolution`` to ``max_resolution`` cells a side, in geometric
steps. Each level stores ``features`` numbers per vertex in a table of ``2**log2_table_size``
rows: coarse levels that fit are indexed directly, finer ones through the paper's spatial
hash (``x·1 ⊕ y·2654435761 ⊕ z·805459861`` mod table size), collisions resolved by training.
A point's encoding is the trilinear interpolation of its cell's 8 corners at every level.

On the CPU, in float32, where a C compiler is found and the points need no gradient (training
and rendering), the encoding and its gradient run in ``kernels/hash_encoding.c``: PyTorch's path
forms each corner's index, weight and row as a tensor of [points, levels, 8], a pass through
memory each. Elsewhere PyTorch computes the same (tests/test_hash_field.py holds the two and
their gradients together).
"""

from __future__ import annotations

import ctypes
import math

import torch
from torch import Tensor, nn

from ..kernels.build import kernel_or_note

_PRIMES = (1, 2654435761, 805459861)
MAX_FEATURES = 8  # hash_encoding.c's
MAX_TABLE_SIZE = 2**32  # hash_encoding.c multiplies in 32 bits: exact modulo tables up to this


class _Tables(ctypes.Structure):
    _fields_ = [("tables", ctypes.c_void_p), ("resolutions", ctypes.c_void_p), ("levels", ctypes.c_int64),
                ("table_size", ctypes.c_int64), ("features", ctypes.c_int64), ("dense_levels", ctypes.c_int64)]


def hash_encoding_library() -> ctypes.CDLL | None:
    """The built kernel, or None (why is said once on stderr)."""
    library, _ = kernel_or_note("hash_encoding", "reading the hash encoding through PyTorch")
    if library is not None:
        library.hash_forward.restype = ctypes.c_int
        library.hash_backward.restype = ctypes.c_int
    return library


def level_resolutions(levels: int, base_resolution: int, max_resolution: int) -> list[int]:
    """Cells a side of each level: geometric from ``base_resolution`` to ``max_resolution``.

    Example:
        >>> level_resolutions(4, 16, 128)
        [16, 32, 64, 128]
    """
    if levels == 1:
        return [base_resolution]
    growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (levels - 1))
    return [int(round(base_resolution * growth**level)) for level in range(levels)]


class HashEncoding(nn.Module):
    """``forward(u [P, 3] in [0, 1]) -> [P, levels · features]``.

    Example:
        >>> encoding = HashEncoding(levels=4, features=2, log2_table_size=12, base_resolution=4, max_resolution=32)
        >>> encoding(torch.rand(5, 3)).shape
        torch.Size([5, 8])
    """

    def __init__(self, levels: int = 16, features: int = 2, log2_table_size: int = 16,
                 base_resolution: int = 16, max_resolution: int = 512) -> None:
        super().__init__()
        self.levels, self.features = levels, features
        self.table_size = 2**log2_table_size
        resolutions = level_resolutions(levels, base_resolution, max_resolution)
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=torch.float32), persistent=False)
        # The coarse levels whose (res+1)³ vertices fit in a table are indexed directly (no
        # collisions); levels are in increasing resolution, so those come first.
        self.dense_levels = sum(1 for r in resolutions if (r + 1) ** 3 <= self.table_size)
        # Instant-NGP's initialisation: small uniform values, so the field starts smooth.
        self.tables = nn.Parameter(torch.empty(levels * self.table_size, features).uniform_(-1e-4, 1e-4))

    @property
    def out_dims(self) -> int:
        return self.levels * self.features

    def _rows(self, vertex: Tensor, first_level: int, dense: bool) -> Tensor:
        """Table rows ``[P, L', 2, 2, 2]`` of the cell corners, from each axis's near and far
        vertex ``vertex [P, L', 3, 2]`` (levels ``first_level`` on). Each axis's term is
        formed before the 8 corners are: ``(a ⊕ b ⊕ c) mod 2^k = (a mod 2^k) ⊕ (b mod 2^k) ⊕
        (c mod 2^k)``, and a level's table offset (a multiple of 2^k) is or-ed into one term."""
        count = vertex.shape[1]
        mask = self.table_size - 1
        offsets = (torch.arange(first_level, first_level + count, device=vertex.device) * self.table_size)
        x, y, z = vertex.unbind(2)  # each [P, L', 2]
        if dense:
            side = (self.resolutions[first_level:first_level + count].long() + 1)[None, :, None]
            x, y, z = x + offsets[None, :, None], y * side, z * side * side
            rows = x[..., :, None, None] + y[..., None, :, None] + z[..., None, None, :]
        else:
            x = ((x * _PRIMES[0]) & mask) | offsets[None, :, None]
            y, z = (y * _PRIMES[1]) & mask, (z * _PRIMES[2]) & mask
            rows = x[..., :, None, None] ^ y[..., None, :, None] ^ z[..., None, None, :]
        return rows

    def forward(self, unit_points: Tensor) -> Tensor:
        if self._compiled_applies(unit_points):
            return _CompiledRead.apply(unit_points.contiguous(), self, self.tables)
        return self.torch_forward(unit_points)

    def _compiled_applies(self, unit_points: Tensor) -> bool:
        return (unit_points.device.type == "cpu" and unit_points.dtype == torch.float32
                and not unit_points.requires_grad and self.tables.dtype == self.resolutions.dtype == torch.float32
                and self.tables.device.type == "cpu" and self.features <= MAX_FEATURES
                and self.table_size <= MAX_TABLE_SIZE
                and hash_encoding_library() is not None)

    def kernel_view(self) -> _Tables:
        """The tables as ``hash_encoding.c`` reads them (``resolutions`` is a float32 buffer)."""
        return _Tables(self.tables.data_ptr(), self.resolutions.data_ptr(), self.levels, self.table_size,
                       self.features, self.dense_levels)

    def torch_forward(self, unit_points: Tensor) -> Tensor:
        """The encoding through PyTorch's tensors (any device; the compiled path's reference)."""
        points = unit_points.float().clamp(0.0, 1.0)
        resolutions = self.resolutions[None, :, None]
        scaled = points[:, None, :] * resolutions  # [P, L, 3]
        cell = torch.minimum(scaled.floor(), resolutions - 1)
        fraction = scaled - cell  # in [0, 1]
        near = cell.long()
        vertex = torch.stack([near, near + 1], dim=-1)  # per axis, near and far vertex [P, L, 3, 2]
        split = self.dense_levels
        rows = torch.cat([self._rows(vertex[:, :split], 0, dense=True),
                          self._rows(vertex[:, split:], split, dense=False)], dim=1)
        wx, wy, wz = torch.stack([1.0 - fraction, fraction], dim=-1).unbind(2)  # each [P, L, 2]
        weights = wx[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :]  # [P, L, 2, 2, 2]
        values = self.tables.index_select(0, rows.reshape(-1)).view(-1, 8, self.features)
        encoded = torch.bmm(weights.reshape(-1, 1, 8), values)  # trilinear interpolation at every level
        return encoded.reshape(points.shape[0], self.out_dims)


def _check(status: int) -> None:
    if status != 0:  # _compiled_applies keeps every call within the kernel's limits
        raise RuntimeError(f"hash_encoding.c refused the call (status {status})")


class _CompiledRead(torch.autograd.Function):
    @staticmethod
    def forward(ctx, unit_points: Tensor, encoding: HashEncoding, tables: Tensor) -> Tensor:
        count = unit_points.shape[0]
        encoded = tables.new_empty((count, encoding.out_dims))
        if count:
            view = encoding.kernel_view()
            _check(hash_encoding_library().hash_forward(
                ctypes.byref(view), ctypes.c_void_p(unit_points.data_ptr()), ctypes.c_int64(count),
                ctypes.c_void_p(encoded.data_ptr()), ctypes.c_int64(torch.get_num_threads())))
        ctx.encoding = encoding
        ctx.save_for_backward(unit_points)
        return encoded

    @staticmethod
    def backward(ctx, grad_encoded: Tensor):
        (unit_points,) = ctx.saved_tensors
        encoding = ctx.encoding
        grad_tables = torch.zeros_like(encoding.tables)
        if unit_points.shape[0]:
            grad = grad_encoded.float().contiguous()
            view = encoding.kernel_view()
            _check(hash_encoding_library().hash_backward(
                ctypes.byref(view), ctypes.c_void_p(unit_points.data_ptr()), ctypes.c_int64(unit_points.shape[0]),
                ctypes.c_void_p(grad.data_ptr()), ctypes.c_void_p(grad_tables.data_ptr()),
                ctypes.c_int64(torch.get_num_threads())))
        return None, None, grad_tables
