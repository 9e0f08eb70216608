"""The training march's compositing of deferred colour in one compiled pass on the CPU, forward
and backward (``kernels/packed_composite.c``): the weights of samples packed per ray, each ray's
opacity, depth, coloured weight and composited appearance features, and their gradients with
respect to the samples' densities and features.

Through PyTorch (``volume_rendering.composite_features_packed``, the reference and the path on
other devices or without a C compiler) the same sums are a dozen passes over the samples, each
an autograd node. Both compute the same values and gradients, to float32 rounding
(tests/test_deferred_colour.py).

Example (where a C compiler is found):
    >>> import torch
    >>> density, features = torch.tensor([1e9, 1.0, 0.5]), torch.tensor([[2.0], [4.0]])
    >>> out = compiled_composite_features(density, torch.ones(3), torch.ones(3), torch.tensor([0, 0, 1]),
    ...                                   torch.tensor([0, 2]), features, rays=2)
    >>> out is None or [round(float(v), 4) for v in out[0]]  # the opacity of each ray
    [1.0, 0.3935]
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from ..kernels.build import load_kernel


class _Composite(ctypes.Structure):
    _fields_ = [("rays", ctypes.c_int64), ("starts", ctypes.c_void_p), ("density", ctypes.c_void_p),
                ("deltas", ctypes.c_void_p), ("t_mid", ctypes.c_void_p), ("feature_row", ctypes.c_void_p),
                ("features", ctypes.c_void_p), ("channels", ctypes.c_int64), ("weights", ctypes.c_void_p),
                ("opacity", ctypes.c_void_p), ("depth", ctypes.c_void_p), ("coloured_weight", ctypes.c_void_p),
                ("accumulated", ctypes.c_void_p), ("grad_opacity", ctypes.c_void_p), ("grad_depth", ctypes.c_void_p),
                ("grad_coloured_weight", ctypes.c_void_p), ("grad_accumulated", ctypes.c_void_p),
                ("grad_density", ctypes.c_void_p), ("grad_features", ctypes.c_void_p)]


def _address(tensor: Tensor | None) -> int | None:
    return None if tensor is None else tensor.data_ptr()


def _settings(tensors: dict[str, Tensor], rays: int, channels: int) -> _Composite:
    settings = _Composite(rays=rays, channels=channels)
    for name, tensor in tensors.items():
        setattr(settings, name, _address(tensor))
    return settings


class _PackedComposite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, density: Tensor, features: Tensor, deltas: Tensor, t_mid: Tensor, starts: Tensor,
                feature_row: Tensor, rays: int, library) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        density, features = density.contiguous(), features.contiguous()
        weights = torch.empty_like(density)
        opacity, depth, coloured = (density.new_empty(rays) for _ in range(3))
        accumulated = features.new_empty((rays, features.shape[1]))
        tensors = dict(starts=starts, density=density, deltas=deltas, t_mid=t_mid, feature_row=feature_row,
                       features=features, weights=weights, opacity=opacity, depth=depth, coloured_weight=coloured,
                       accumulated=accumulated)
        library.composite_forward(ctypes.byref(_settings(tensors, rays, features.shape[1])),
                                  ctypes.c_int64(torch.get_num_threads()))
        ctx.save_for_backward(density, features, deltas, t_mid, starts, feature_row, weights)
        ctx.rays, ctx.library = rays, library
        return opacity, depth, coloured, accumulated

    @staticmethod
    def backward(ctx, grad_opacity, grad_depth, grad_coloured, grad_accumulated):
        density, features, deltas, t_mid, starts, feature_row, weights = ctx.saved_tensors
        rays = ctx.rays
        grads = [g.contiguous() if g is not None else torch.zeros(shape, dtype=density.dtype)
                 for g, shape in ((grad_opacity, rays), (grad_depth, rays), (grad_coloured, rays),
                                  (grad_accumulated, (rays, features.shape[1])))]
        grad_density, grad_features = torch.empty_like(density), torch.zeros_like(features)
        tensors = dict(starts=starts, density=density, deltas=deltas, t_mid=t_mid, feature_row=feature_row,
                       features=features, weights=weights, grad_opacity=grads[0], grad_depth=grads[1],
                       grad_coloured_weight=grads[2], grad_accumulated=grads[3], grad_density=grad_density,
                       grad_features=grad_features)
        ctx.library.composite_backward(ctypes.byref(_settings(tensors, rays, features.shape[1])),
                                       ctypes.c_int64(torch.get_num_threads()))
        return grad_density, grad_features, None, None, None, None, None, None


def compiled_composite_library() -> ctypes.CDLL | None:
    library, _ = load_kernel("packed_composite")
    return library


def compiled_composite_features(density: Tensor, deltas: Tensor, t_mid: Tensor, ray: Tensor, coloured: Tensor,
                                features: Tensor, rays: int) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """``volume_rendering.composite_features_packed`` in the compiled pass: each ray's opacity
    ``[R]``, depth ``[R]``, coloured weight ``[R]`` and composited features ``[R, C]``, with
    gradients for ``density`` and ``features``; None where the pass does not apply (not on the
    CPU in float32, no C compiler)."""
    if (density.device.type != "cpu" or density.dtype != torch.float32 or features.dtype != torch.float32
            or features.device.type != "cpu"):
        return None
    library = compiled_composite_library()
    if library is None:
        return None
    counts = torch.bincount(ray, minlength=rays)
    starts = torch.zeros(rays + 1, dtype=torch.int64)
    torch.cumsum(counts, 0, out=starts[1:])
    feature_row = torch.full_like(ray, -1).index_put_((coloured,), torch.arange(coloured.numel()))
    as_float = [t.float().contiguous() for t in (deltas, t_mid)]
    return _PackedComposite.apply(density, features, *as_float, starts, feature_row.contiguous(), rays, library)
