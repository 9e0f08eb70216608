"""The grid field's training pass over the training march's lit samples, deferred colour, in
one compiled call forward and one backward on the CPU (``kernels/lit_pass.h``).

Between the compiled march and the colour network, PyTorch ran a dozen small operations and
their autograd nodes a step: each lit sample's interval and point from its index, which samples
get a colour, the density grid read again with gradients and its softplus, the appearance grid
read at the coloured samples, the compositing; and backward each again. The march now records
each lit sample's midpoint, length, density pre-activation and point as it finds it
(``compiled_march.compiled_lit_samples(record=True)``), and one call does the rest: each ray's
opacity, depth, coloured weight and composited appearance features, and backward the gradient
into both grids' touched rows (marked for ``SparseRowAdam``). The colour network then shades
each ray's features as before (``volume_rendering.shade_rays``).

The PyTorch path (``GridField.forward`` and ``volume_rendering.composite_features_packed``) is
the reference and runs wherever this does not (CUDA, MPS, no C compiler, region-aware colour,
per-sample colour): both give the same outputs and gradients to float32 rounding
(tests/test_compiled_lit_pass.py).

Example (where a C compiler is found):
    >>> import torch
    >>> from nerf_backend.field_components.grid_encodings import VectorMatrixGrid
    >>> density, appearance = VectorMatrixGrid(8, (5, 5, 5)), VectorMatrixGrid(8, (5, 5, 5))
    >>> lit = torch.tensor([0, 1, 5])  # ray 0's steps 0 and 1, ray 1's step 2 (3 steps a ray)
    >>> record = torch.tensor([[1.0, 0.5, 3.0, 0.0, 0.0, 0.0], [1.5, 0.5, 3.0, 0.1, 0.0, 0.0],
    ...                        [2.0, 0.5, -30.0, 0.0, 0.2, 0.0]])
    >>> out = lit_pass(density, appearance, 1.0, 0.0, lit, torch.ones(3), record, rays=2, steps=3)
    >>> out is None or [round(v, 3) for v in out[0].detach().tolist()]  # each ray's opacity
    [0.953, 0.0]
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from ..kernels.build import kernel_or_note
from .compiled_grid import (CHANNEL_BLOCK, KernelComponent, gradient_buffers, grid_parameters, kernel_components,
                            rows_in_place)


class _LitPass(ctypes.Structure):
    _fields_ = [("rays", ctypes.c_int64), ("samples", ctypes.c_int64), ("steps", ctypes.c_int64),
                ("lit", ctypes.c_void_p), ("march_weight", ctypes.c_void_p), ("record", ctypes.c_void_p),
                ("density_scale", ctypes.c_float), ("density_shift", ctypes.c_float),
                ("coloured_weight_floor", ctypes.c_float), ("coloured_weight_share", ctypes.c_float),
                ("density", KernelComponent * 3), ("appearance", KernelComponent * 3), ("width", ctypes.c_int64),
                ("starts", ctypes.c_void_p), ("feature_row", ctypes.c_void_p), ("coloured_points", ctypes.c_void_p),
                ("features", ctypes.c_void_p), ("weights", ctypes.c_void_p), ("sigma", ctypes.c_void_p),
                ("opacity", ctypes.c_void_p),
                ("depth", ctypes.c_void_p), ("coloured_weight", ctypes.c_void_p), ("accumulated", ctypes.c_void_p),
                ("coloured", ctypes.c_int64), ("grad_opacity", ctypes.c_void_p), ("grad_depth", ctypes.c_void_p),
                ("grad_coloured_weight", ctypes.c_void_p), ("grad_accumulated", ctypes.c_void_p),
                ("grad_sum", ctypes.c_void_p), ("grad_features", ctypes.c_void_p)]


def _library() -> ctypes.CDLL | None:
    library, _ = kernel_or_note("vm_grid", "training the grids through PyTorch")
    if library is not None:
        library.lit_pass_forward.restype = ctypes.c_int64
        library.lit_pass_backward.restype = ctypes.c_int
    return library


def _point(settings: _LitPass, **tensors: Tensor) -> None:
    for name, tensor in tensors.items():
        setattr(settings, name, tensor.data_ptr())


class _LitComposite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, lit: Tensor, march_weight: Tensor, record: Tensor, rays: int, steps: int, scale: float,
                shift: float, colouring: tuple[float, float], told: dict, grids,
                *parameters: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        library = _library()
        samples, width = lit.shape[0], grids[1].out_dims
        tables = [rows_in_place(p) for p in parameters]
        settings = _LitPass(rays=rays, samples=samples, steps=steps, density_scale=scale, density_shift=shift,
                            coloured_weight_floor=colouring[0], coloured_weight_share=colouring[1], width=width)
        components = kernel_components(grids, tables, None, None, None, None)
        settings.density[:], settings.appearance[:] = components[:3], components[3:]
        kept = dict(starts=lit.new_empty(rays + 1), feature_row=lit.new_empty(samples),
                    coloured_points=record.new_empty((samples, 3)), features=record.new_empty((samples, width)),
                    weights=record.new_empty(samples), sigma=record.new_empty(samples))
        out = dict(opacity=record.new_empty(rays), depth=record.new_empty(rays),
                   coloured_weight=record.new_empty(rays), accumulated=record.new_empty((rays, width)))
        _point(settings, lit=lit, march_weight=march_weight, record=record, **kept, **out)
        coloured = library.lit_pass_forward(ctypes.byref(settings), ctypes.c_int64(torch.get_num_threads()))
        if coloured < 0:
            raise RuntimeError(f"vm_grid.c's lit pass refused its input (status {coloured})")
        ctx.settings, ctx.grids, ctx.library, ctx.tables = settings, grids, library, tables
        ctx.coloured = told["coloured"] = coloured
        ctx.save_for_backward(lit, march_weight, record, *kept.values(), *parameters)
        return out["opacity"], out["depth"], out["coloured_weight"], out["accumulated"]

    @staticmethod
    def backward(ctx, grad_opacity, grad_depth, grad_coloured_weight, grad_accumulated):
        lit, march_weight, record, *kept_and_parameters = ctx.saved_tensors
        parameters = kept_and_parameters[6:]
        settings, rays, width = ctx.settings, ctx.settings.rays, ctx.settings.width
        grads = [g.float().contiguous() if g is not None else torch.zeros(shape)
                 for g, shape in ((grad_opacity, rays), (grad_depth, rays), (grad_coloured_weight, rays),
                                  (grad_accumulated, (rays, width)))]
        row_grads, touched, returned = gradient_buffers(ctx.grids, list(parameters))
        components = kernel_components(ctx.grids, ctx.tables, None, None, row_grads, touched)
        settings.density[:], settings.appearance[:] = components[:3], components[3:]
        scratch = dict(grad_sum=record.new_empty(lit.shape[0]), grad_features=record.new_empty((ctx.coloured, width)))
        _point(settings, grad_opacity=grads[0], grad_depth=grads[1], grad_coloured_weight=grads[2],
               grad_accumulated=grads[3], **scratch)
        ctx.library.lit_pass_backward(ctypes.byref(settings), ctypes.c_int64(torch.get_num_threads()))
        return (None,) * 10 + tuple(returned)


def lit_pass_applies(density_grid, appearance_grid) -> bool:
    """Whether ``lit_pass`` can run these grids (CPU, float32, channels in blocks of 8, a C compiler)."""
    return (all(grid.channels % CHANNEL_BLOCK == 0 for grid in (density_grid, appearance_grid))
            and all(p.dtype == torch.float32 and p.device.type == "cpu"
                    for grid in (density_grid, appearance_grid) for p in grid.parameters())
            and _library() is not None)


def lit_pass(density_grid, appearance_grid, scale: float, shift: float, lit: Tensor, march_weight: Tensor,
             record: Tensor, rays: int, steps: int,
             colouring: tuple[float, float] = (1e-4, 1e-2)) -> tuple[Tensor, Tensor, Tensor, Tensor, int] | None:
    """Each ray's opacity ``[R]``, depth ``[R]``, coloured weight ``[R]`` and composited
    appearance features ``[R, 3·C]``, and the count of coloured samples, from the training
    march's lit samples (``lit [L]``, their weights ``march_weight [L]`` and ``record [L, 6]``:
    ``compiled_lit_samples(record=True)``), density ``scale · softplus(Σ density features +
    shift)``; differentiable with respect to both grids' planes and lines. ``colouring``: which
    samples get a colour, as ``marcher.colour_worthy`` chooses them (its weight floor and share
    of the ray's heaviest).
    None where it does not apply (``lit_pass_applies``)."""
    if not lit_pass_applies(density_grid, appearance_grid):
        return None
    grids, told = (density_grid, appearance_grid), {}  # told: the coloured count (autograd returns tensors)
    out = _LitComposite.apply(lit.contiguous(), march_weight.float().contiguous(), record.float().contiguous(),
                              rays, steps, float(scale), float(shift), colouring, told, grids,
                              *grid_parameters(grids))
    return (*out, told["coloured"])
