"""Volume rendering along rays (the paper's Eq. 3), in the numerically stable form.

Functions take per-sample tensors shaped ``[R, S]`` (R rays, S samples each), or samples
packed per ray (``[N]`` with the ray of each, nerfacc's packed layout: only the samples that
hold density, however many a ray has), and are free of any model: the caller evaluates the
field, these integrate it (the nerfacc split).

Transmittance is ``exp(-exclusive_cumsum(σ·δ))`` rather than ``cumprod(1 - α + ε)``: the
sum never loses precision as opacity approaches 1, and there is no ε to bias empty rays.
"""

from __future__ import annotations

import torch
from torch import Tensor


def render_weights(density: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """Per-sample weights ``w_i = T_i · (1 - exp(-σ_i δ_i))`` and transmittance ``T_i``.

    Args:
        density: ``[R, S]`` non-negative σ at each sample.
        deltas: ``[R, S]`` non-negative interval lengths δ.

    Returns:
        ``weights [R, S]`` (non-negative, summing to ``1 - T_final`` ≤ 1) and the
        transmittance ``[R, S]`` in front of each sample.

    Example:
        >>> w, t = render_weights(torch.tensor([[1e9, 1.0]]), torch.tensor([[1.0, 1.0]]))
        >>> w.tolist()  # an opaque first sample takes all the weight
        [[1.0, 0.0]]
    """
    optical_depth = density * deltas
    alpha = -torch.expm1(-optical_depth)  # 1 - exp(-x), exact for tiny x
    accumulated = torch.cumsum(optical_depth, dim=-1)
    exclusive = torch.cat([torch.zeros_like(accumulated[..., :1]), accumulated[..., :-1]], dim=-1)
    transmittance = torch.exp(-exclusive)
    return transmittance * alpha, transmittance


def accumulate(weights: Tensor, values: Tensor) -> Tensor:
    """Σ_i w_i · v_i over samples: ``weights [R, S]``, ``values [R, S, C]`` → ``[R, C]``."""
    return torch.einsum("rs,rsc->rc", weights, values)


def composite_rgb(weights: Tensor, rgb: Tensor, background: Tensor | float) -> Tensor:
    """Colour of each ray over a background: ``Σ w·c + (1 - Σ w)·background``."""
    opacity = weights.sum(dim=-1, keepdim=True)
    return accumulate(weights, rgb) + (1.0 - opacity) * background


def expected_depth(weights: Tensor, t_mid: Tensor) -> Tensor:
    """Weight-averaged distance ``Σ w·t`` (not normalised: background contributes 0)."""
    return (weights * t_mid).sum(dim=-1)


def render_weights_packed(density: Tensor, deltas: Tensor, ray: Tensor) -> tuple[Tensor, Tensor]:
    """``render_weights`` for samples packed per ray: ``density [N]`` and ``deltas [N]`` of the
    samples of rays ``ray [N]``, a ray's samples together and in order along it (ascending
    ``ray``); samples left out between them hold no density, so they change nothing.

    The optical depth in front of a sample is a running sum over every ray's samples less its
    value at the ray's first one, summed in float64: in float32, a batch of opaque rays sums to
    depths whose last digits are larger than a translucent sample's own.

    Example:
        >>> w, t = render_weights_packed(torch.tensor([1e9, 1.0, 0.5]), torch.ones(3), torch.tensor([0, 0, 1]))
        >>> w.tolist()  # ray 0: its opaque first sample takes everything; ray 1: 1 - e^-0.5
        [1.0, 0.0, 0.39346933364868164]
    """
    optical_depth = density * deltas
    wide = optical_depth.double()
    before = torch.cumsum(wide, 0) - wide
    first = torch.searchsorted(ray, ray)  # each sample's ray's first sample
    transmittance = torch.exp(-(before - before.index_select(0, first))).to(density.dtype)
    return transmittance * -torch.expm1(-optical_depth), transmittance


def sum_per_ray(values: Tensor, ray: Tensor, rays: int) -> Tensor:
    """Σ over each ray's packed samples: ``values [N, ...]`` of rays ``ray [N]`` → ``[rays, ...]``.

    Example:
        >>> sum_per_ray(torch.tensor([0.5, 0.25, 1.0]), torch.tensor([0, 0, 2]), 3).tolist()
        [0.75, 0.0, 1.0]
    """
    return values.new_zeros((rays, *values.shape[1:])).index_add(0, ray, values)
