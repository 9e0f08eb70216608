"""Volume rendering along rays (the paper's Eq. 3), in the numerically stable form.

Functions take per-sample tensors shaped ``[R, S]`` (R rays, S samples each) and are free of
any model: the caller evaluates the field, these integrate it (the nerfacc split).

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
