"""The factorised grids' read and its gradient in one compiled pass over packed samples, for
training on the CPU (``kernels/vm_grid.c``).

PyTorch's CPU path reads each plane and line with ``embedding_bag`` and its backward sorts the
indices and fills a dense gradient of the whole grid, per plane, on one thread: on lego at
800×800 (22 400 lit samples a step, a 147³ grid) the two grids' forward and backward took 79 ms
of a 121 ms step. Here the planes are read in place (they are stored channel-last:
``VectorMatrixGrid``'s notes), each sample's 4 plane rows and 2 line rows once, and the gradient
is added only into the rows the samples touched; the rows are marked, so ``SparseRowAdam``
updates only those (``training/sparse_adam.py``).

It applies on the CPU, in float32, where a C compiler is found and the points need no gradient
(the grid field's training step); elsewhere the grids read through PyTorch, which computes the
same features (tests/test_compiled_grid.py checks both and their gradients).

Example (where a C compiler is found):
    >>> import torch
    >>> from nerf_backend.field_components.grid_encodings import VectorMatrixGrid
    >>> grid = VectorMatrixGrid(channels=4, vertices=(9, 7, 5))
    >>> x = torch.rand(100, 3) * 2 - 1
    >>> compiled = read_grids([grid], x)
    >>> compiled is None or bool(torch.allclose(compiled, grid(x), atol=1e-6))
    True
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from ..kernels.build import kernel_or_note

# VectorMatrixGrid's components: (plane axes, line axis), as grid_encodings._MODES.
_MODES = (((0, 1), 2), ((0, 2), 1), ((1, 2), 0))
# vm_grid.c's BLOCK (channels go in vectors of 8: a grid of other channel counts reads through
# PyTorch) and MAX_TASKS / 3.
CHANNEL_BLOCK = 8
MAX_GRIDS = 5


class KernelComponent(ctypes.Structure):
    _fields_ = [("plane", ctypes.c_void_p), ("line", ctypes.c_void_p), ("features", ctypes.c_void_p),
                ("grad", ctypes.c_void_p), ("plane_grad", ctypes.c_void_p), ("line_grad", ctypes.c_void_p),
                ("plane_touched", ctypes.c_void_p), ("line_touched", ctypes.c_void_p),
                ("row_stride", ctypes.c_int64), ("axis_a", ctypes.c_int32), ("axis_b", ctypes.c_int32),
                ("axis_c", ctypes.c_int32), ("na", ctypes.c_int32), ("nb", ctypes.c_int32), ("nc", ctypes.c_int32),
                ("channels", ctypes.c_int32), ("pad", ctypes.c_int32)]




def compiled_grid_library() -> ctypes.CDLL | None:
    """The built kernel, or None (why is said once on stderr: the grids then train through
    PyTorch, slower)."""
    library, _ = kernel_or_note("vm_grid", "training the grids through PyTorch")
    if library is None:
        return None
    library.vm_forward.restype = ctypes.c_int
    library.vm_backward.restype = ctypes.c_int
    library.vm_dense_sum.restype = None
    library.sparse_adam.restype = ctypes.c_int64
    library.sparse_adam.argtypes = ([ctypes.c_void_p] * 6 + [ctypes.c_int64] * 3 + [ctypes.c_float] * 4
                                    + [ctypes.c_int64])
    return library


def channel_rows(parameter: Tensor) -> Tensor:
    """A plane ``[1, C, Na, Nb]`` or line ``[1, C, N, 1]`` as its table of channel rows
    ``[Na·Nb, C]`` (``[N, C]``): a view of a channel-last parameter, else a copy."""
    channels = parameter.shape[1]
    return parameter[0].permute(1, 2, 0).reshape(-1, channels)


def rows_in_place(parameter: Tensor) -> Tensor:
    rows = channel_rows(parameter.detach())
    return rows if rows.is_contiguous() else rows.contiguous()


def compiled_applies(x: Tensor, grids) -> bool:
    """Whether ``read_grids`` can read these grids at these points."""
    return (x.device.type == "cpu" and x.dtype == torch.float32 and not x.requires_grad
            and all(grid.channels % CHANNEL_BLOCK == 0 for grid in grids) and len(grids) <= MAX_GRIDS
            and all(p.dtype == torch.float32 for grid in grids for p in grid.parameters())
            and compiled_grid_library() is not None)


def kernel_components(grids, tables: list[Tensor], features: Tensor | None, grad: Tensor | None,
                      grads: list[Tensor] | None, touched: list[Tensor | None] | None) -> ctypes.Array:
    """The grids' components as ``vm_grid.c`` reads them (3 a grid): their ``tables`` (each
    parameter's rows, ``grid_parameters``' order), and where given the columns of ``features``
    or ``grad`` that are theirs, and the row buffers ``grads`` and marks ``touched`` that their
    gradient goes into."""
    components = (KernelComponent * (3 * len(grids)))()
    column, index = 0, 0
    for grid in grids:
        vertices, channels = grid.vertices, grid.channels
        for mode, ((a, b), c) in enumerate(_MODES):
            plane, line = tables[2 * index], tables[2 * index + 1]
            entry = components[index]
            entry.plane, entry.line = plane.data_ptr(), line.data_ptr()
            entry.axis_a, entry.axis_b, entry.axis_c = a, b, c
            entry.na, entry.nb, entry.nc = vertices[a], vertices[b], vertices[c]
            entry.channels = channels
            if features is not None:
                entry.features = features.data_ptr() + 4 * column
                entry.row_stride = features.shape[1]
            if grad is not None:
                entry.grad = grad.data_ptr() + 4 * column
                entry.row_stride = grad.shape[1]
            if grads is not None:
                entry.plane_grad, entry.line_grad = grads[2 * index].data_ptr(), grads[2 * index + 1].data_ptr()
                if touched is not None:
                    plane_marks, line_marks = touched[2 * index], touched[2 * index + 1]
                    entry.plane_touched = plane_marks.data_ptr() if plane_marks is not None else None
                    entry.line_touched = line_marks.data_ptr() if line_marks is not None else None
            column += channels
            index += 1
    return components


def grid_parameters(grids) -> list[Tensor]:
    """Each grid's planes and lines, in the kernel's order: plane 0, line 0, plane 1, ..."""
    return [p for grid in grids for pair in zip(grid.planes, grid.lines) for p in pair]


class _ReadGrids(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, grids, *parameters: Tensor) -> Tensor:
        library = compiled_grid_library()
        x = x.contiguous()
        tables = [rows_in_place(p) for p in parameters]
        features = x.new_empty((x.shape[0], sum(grid.out_dims for grid in grids)))
        if x.shape[0]:
            components = kernel_components(grids, tables, features, None, None, None)
            _check(library.vm_forward(components, len(components), ctypes.c_void_p(x.data_ptr()),
                                      ctypes.c_int64(x.shape[0]), ctypes.c_int64(torch.get_num_threads())))
        ctx.grids = grids
        ctx.save_for_backward(x, *parameters)
        return features

    @staticmethod
    def backward(ctx, grad_features: Tensor):
        x, *parameters = ctx.saved_tensors
        grids = ctx.grids
        grad = grad_features.float().contiguous()
        tables = [rows_in_place(p) for p in parameters]
        grads, touched, returned = gradient_buffers(grids, parameters)
        if x.shape[0]:
            components = kernel_components(grids, tables, None, grad, grads, touched)
            _check(compiled_grid_library().vm_backward(components, len(components), ctypes.c_void_p(x.data_ptr()),
                                                       ctypes.c_int64(x.shape[0]),
                                                       ctypes.c_int64(torch.get_num_threads())))
        return (None, None, *returned)


def gradient_buffers(grids, parameters: list[Tensor]) -> tuple[list[Tensor], list[Tensor | None], list[Tensor | None]]:
    """Where the kernel adds the gradient of each of ``grids``' ``parameters`` (6 a grid, in
    ``_parameters``' order): the rows of the grid's own buffers, marked, where the optimiser
    updates rows (``training/sparse_adam.RowSparseAdam``), else new dense tensors; then the
    row buffers, their marks (or None), and what autograd is to return for each parameter
    (None where the rows took it)."""
    grads, touched, returned = [], [], []
    for g, grid in enumerate(grids):
        own = parameters[6 * g:6 * g + 6]
        sink = _gradient_sink(grid, own)
        if sink is not None:  # the rows go to the grid's own buffers, for SparseRowAdam
            grads += sink.gradients
            touched += sink.marks
            returned += [None] * 6
        else:
            dense = [torch.zeros(p.shape[0], p.shape[2], p.shape[3], p.shape[1]) for p in own]
            grads += dense
            touched += [None] * 6
            returned += [d.permute(0, 3, 1, 2) for d in dense]
    return grads, touched, returned


def _check(status: int) -> None:
    if status != 0:  # compiled_applies keeps every call within the kernel's limits
        raise RuntimeError(f"vm_grid.c refused the call (status {status})")


def density_components(grid) -> tuple[ctypes.Array, list[Tensor]] | None:
    """The grid's three components as ``vm_grid.c`` reads them (what its training march sums
    into a density) and the tables they point into (keep them alive while it reads); None where
    the kernel cannot read this grid."""
    if grid.channels % CHANNEL_BLOCK or grid.channels > 64 or compiled_grid_library() is None or any(
            p.dtype != torch.float32 or p.device.type != "cpu" for p in grid.parameters()):
        return None
    tables = [rows_in_place(p) for p in grid_parameters([grid])]
    return kernel_components([grid], tables, None, None, None, None), tables


def dense_sum(grid) -> Tensor | None:
    """The grid's features summed at every vertex, ``[Nz, Ny, Nx]`` (``VectorMatrixGrid.dense_sum``),
    in one compiled pass that writes each vertex once (``vm_dense_sum``); None where it does not
    apply (not float32 on the CPU, a gradient wanted, no compiler). Lego's thirty-minute grid
    (310 × 533 × 342 vertices, 2 AVX2 cores): 0.47 s through PyTorch's three matrix products.

    Example (where a C compiler is found):
        >>> from nerf_backend.field_components.grid_encodings import VectorMatrixGrid
        >>> grid = VectorMatrixGrid(channels=4, vertices=(9, 7, 5))
        >>> summed = dense_sum(grid)
        >>> summed is None or bool(torch.allclose(summed, grid._dense_sum_float32(), atol=1e-5))
        True
    """
    parameters = list(grid.parameters())
    if (any(p.dtype != torch.float32 or p.device.type != "cpu" for p in parameters)
            or (torch.is_grad_enabled() and any(p.requires_grad for p in parameters))
            or compiled_grid_library() is None):
        return None
    (nx, ny, nz), channels = grid.vertices, grid.channels
    (xy, xz, yz), (z_line, y_line, x_line) = [p.detach()[0] for p in grid.planes], [
        line.detach()[0, :, :, 0] for line in grid.lines]
    # x fastest for the x line and the two planes that hold x: a vertex row is then contiguous vectors.
    x_columns, xy_columns, xz_columns = (x_line.contiguous(), xy.permute(2, 0, 1).contiguous(),
                                         xz.permute(2, 0, 1).contiguous())
    yz_rows, y_rows, z_rows = (yz.permute(1, 2, 0).contiguous(), y_line.T.contiguous(), z_line.T.contiguous())
    out = torch.empty((nz, ny, nx))
    compiled_grid_library().vm_dense_sum(
        *(ctypes.c_void_p(t.data_ptr()) for t in (x_columns, xy_columns, xz_columns, yz_rows, y_rows, z_rows)),
        *(ctypes.c_int64(n) for n in (nx, ny, nz, channels)), ctypes.c_void_p(out.data_ptr()),
        ctypes.c_int64(torch.get_num_threads()))
    return out


def _gradient_sink(grid, parameters):
    """The grid's row-gradient buffers where an optimiser that updates rows gave it some for
    these very parameters (``training/sparse_adam.RowSparseAdam``), else None: dense gradients
    through autograd."""
    sink = getattr(grid, "row_gradients", None)
    return sink if sink is not None and sink.serves(list(parameters)) else None


def read_grids(grids, x: Tensor) -> Tensor | None:
    """The features of every grid at ``x [P, 3]`` in [-1, 1], side by side (``[P, Σ 3·C]``, each
    grid's ``forward`` in turn), with gradients for their planes and lines; None where the
    compiled path does not apply (``compiled_applies``)."""
    if not compiled_applies(x, grids):
        return None
    return _ReadGrids.apply(x, tuple(grids), *grid_parameters(grids))
