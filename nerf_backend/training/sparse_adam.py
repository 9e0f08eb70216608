"""Adam that updates only the grid rows a step touched (DVGO's and Instant-NGP's masked Adam),
for the grids trained through a compiled kernel on the CPU: the factorised grids' planes and
lines (``compiled_grid``) and the sparse voxel grid's table (``sparse_grid``).

A step of 1 024 rays on lego at 800×800 touches a few percent of a grid's rows; dense Adam
reads and writes all of them (p, g, m, v: 28 bytes a parameter) and the dense gradient must be
zeroed each step besides. Here the kernel's backward adds each sample's gradient into a
buffer of the grid's own and marks the rows; ``vm_grid.c``'s ``sparse_adam`` then updates the
marked rows, zeroes their gradient and clears their marks, and nothing else is touched.

A row that skipped k steps has its moments decayed by β^k before its update, as dense Adam's
would have been by k steps of zero gradient; the drift dense Adam would have given its value over
those k steps (its momentum carrying on) is not applied: the rows a step leaves are those no
ray of it saw. Bias correction uses the run's step count, as dense Adam's does. Every other
parameter (the networks, a grid read through PyTorch) goes through ``Adam`` (training/adam.py):
a parameter with a ``.grad`` is dense.

Example:
    >>> import torch
    >>> from nerf_backend.field_components.grid_encodings import VectorMatrixGrid
    >>> grid = VectorMatrixGrid(channels=8, vertices=6)
    >>> optimiser = RowSparseAdam([{"params": list(grid.parameters()), "lr": 0.1}], grids=[grid])
    >>> x = torch.zeros(1, 3)  # the centre: 4 rows of each plane, 2 of each line
    >>> grid(x).sum().backward()
    >>> before = grid.planes[0].detach().clone()
    >>> optimiser.step()
    >>> changed = (grid.planes[0] != before).any(dim=1).sum().item()
    >>> changed == 4 or optimiser.rows_updated is None  # None: no compiler, dense Adam did it
    True
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor
from torch.autograd.graph import increment_version

from ..field_components.compiled_grid import channel_rows, compiled_grid_library
from .adam import Adam


def _rows_like(parameter: Tensor) -> Tensor:
    """Zeros laid out as ``parameter``'s rows are: channel-last for a plane or line, row-major
    for a table."""
    if parameter.dim() == 4:
        return torch.zeros_like(parameter, memory_format=torch.channels_last)
    return torch.zeros_like(parameter, memory_format=torch.contiguous_format)


def _laid_out_in_rows(tensor: Tensor) -> bool:
    if tensor.dim() == 4:
        return tensor.is_contiguous(memory_format=torch.channels_last)
    return tensor.is_contiguous()


def _in_rows(tensor: Tensor) -> Tensor:
    return tensor.contiguous(memory_format=torch.channels_last) if tensor.dim() == 4 else tensor.contiguous()


def _row_count(parameter: Tensor) -> int:
    return channel_rows(parameter).shape[0] if parameter.dim() == 4 else parameter.shape[0]


class RowGradients:
    """A grid's gradient buffers (laid out as its parameters' rows) and row marks, which the
    compiled backward fills for the parameters it was made for."""

    def __init__(self, parameters: list[Tensor]) -> None:
        self.pointers = [(p.data_ptr(), tuple(p.shape)) for p in parameters]
        self.gradients = [_rows_like(p) for p in parameters]
        self.marks = [torch.zeros(_row_count(p), dtype=torch.uint8) for p in parameters]

    def serves(self, parameters: list[Tensor]) -> bool:
        """Whether these are still the parameters the buffers were made for (a grown grid has
        new ones: its gradient then goes through autograd until a new optimiser attaches)."""
        return [(p.data_ptr(), tuple(p.shape)) for p in parameters] == self.pointers


class RowSparseAdam(Adam):
    """``Adam`` whose ``grids``' row parameters (each grid's
    ``sparse_row_parameters()``), when their gradient came through the compiled kernel, are
    updated row by row (see the module's notes); ``rows_updated``: the
    grid rows the last step updated, ``floats_updated`` the values (the touched rows' and the dense
    parameters'); both None where no compiler is found: then every parameter is dense."""

    def __init__(self, params, grids, **adam) -> None:
        super().__init__(params, **adam)
        self.rows_updated: int | None = None
        # Values the last step updated: the touched rows' and every dense parameter's (what
        # bench-step counts the optimiser's and the grids' memory traffic by).
        self.floats_updated: int | None = None
        self.row_floats_updated: int | None = None  # of those, the grid rows' (the rows the step read)
        self._library = compiled_grid_library()
        self._sparse: dict[int, tuple[RowGradients, int]] = {}
        if self._library is None:
            return
        for grid in grids:
            parameters = grid.sparse_row_parameters()
            sink = RowGradients(parameters)
            grid.row_gradients = sink
            for index, parameter in enumerate(parameters):
                self._sparse[id(parameter)] = (sink, index)

    @torch.no_grad()
    def step(self, closure=None):
        if self._library is None:
            return super().step(closure)
        sparse = []
        for group in self.param_groups:
            for parameter in group["params"]:
                entry = self._sparse.get(id(parameter))
                if entry is None or entry[0].pointers[entry[1]] != (parameter.data_ptr(), tuple(parameter.shape)):
                    continue  # not a grid's, or no longer the parameter the buffers were made for
                sink, index = entry
                if parameter.grad is not None:  # read through PyTorch this step: dense, with the rows
                    parameter.grad.add_(sink.gradients[index])
                    sink.gradients[index].zero_()
                    sink.marks[index].zero_()
                else:
                    sparse.append((group, parameter, sink, index))
        dense = sum(p.numel() for group in self.param_groups for p in group["params"] if p.grad is not None)
        loss = super().step(closure)  # the dense parameters (those with a .grad)
        rows = floats = 0
        for group, parameter, sink, index in sparse:
            updated = self._sparse_step(group, parameter, sink.gradients[index], sink.marks[index])
            # The kernel wrote the values through a pointer, which PyTorch does not see: its
            # version counter moves on here, as an in-place operation's does, so that what is
            # kept of the old values (tensor_keys.kept_derived: the half-precision tables, the
            # dense density) is made again. Without it, the half tables made at training's
            # first validation stayed, and lego's later validations scored about 20 dB.
            increment_version(parameter)
            rows += updated
            floats += updated * parameter.shape[1]
        self.rows_updated, self.row_floats_updated, self.floats_updated = rows, floats, floats + dense
        return loss

    def _sparse_step(self, group: dict, parameter: Tensor, gradient: Tensor, marks: Tensor) -> int:
        state = self.state[parameter]
        rows = marks.shape[0]
        if "last_step" not in state or state["last_step"].shape != (rows,) or not all(
                _laid_out_in_rows(state[key]) for key in ("exp_avg", "exp_avg_sq")):
            self._prepare_state(state, parameter, rows)
        step = state["step"]
        step += 1
        beta1, beta2 = group["betas"]
        # As many threads as PyTorch's, each over its share of the rows (a row's update is its
        # own, so the result is the same): on lego's 256-vertex grids (3.6 M values a step) two
        # took the optimiser from 7.1-7.9 to 4.4-4.8 ms a step, each thread's misses in flight
        # beside the other's (on session 46's 147³ grids two were no faster).
        return int(self._library.sparse_adam(
            parameter.data_ptr(), gradient.data_ptr(), state["exp_avg"].data_ptr(), state["exp_avg_sq"].data_ptr(),
            marks.data_ptr(), state["last_step"].data_ptr(), rows, parameter.shape[1], int(step), float(group["lr"]),
            float(beta1), float(beta2), float(group["eps"]), torch.get_num_threads()))

    @staticmethod
    def _prepare_state(state: dict, parameter: Tensor, rows: int) -> None:
        """A parameter's first sparse step, or its state as a checkpoint of dense Adam left it
        (another layout, no row steps): the moments channel-last, each row as if updated at the
        last step."""
        if "exp_avg" not in state:
            state["step"] = torch.zeros((), dtype=torch.float32)
            state["exp_avg"] = _rows_like(parameter)
            state["exp_avg_sq"] = _rows_like(parameter)
        for key in ("exp_avg", "exp_avg_sq"):
            state[key] = _in_rows(state[key])
        if "last_step" not in state or state["last_step"].shape != (rows,):
            state["last_step"] = torch.full((rows,), float(state["step"]), dtype=torch.float32)
