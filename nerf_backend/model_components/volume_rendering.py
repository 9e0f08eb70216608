"""Volume rendering along rays (the paper's Eq. 3), in the numerically stable form.

Functions take per-sample tensors shaped ``[R, S]`` (R rays, S samples each), or samples
packed per ray (``[N]`` with the ray of each, nerfacc's packed layout: only the samples that
hold density, however many a ray has), and are free of any model: the caller evaluates the
field, these integrate it (the nerfacc split).

Transmittance is ``exp(-exclusive_cumsum(σ·δ))`` rather than ``cumprod(1 - α + ε)``: the
sum never loses precision as opacity approaches 1, and there is no ε to bias empty rays.
"""

from __future__ import annotations

from typing import Callable

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
    # Each sample's ray's first sample: the latest index at which the ray changed (a search of
    # the sorted rays took 0.29 ms for lego's 28 k lit samples of a step; this, 0.05).
    starts = torch.ones_like(ray, dtype=torch.bool)
    starts[1:] = ray[1:] != ray[:-1]
    first = torch.cummax(torch.arange(ray.numel(), device=ray.device) * starts, 0).values
    transmittance = torch.exp(-(before - before.index_select(0, first))).to(density.dtype)
    return transmittance * -torch.expm1(-optical_depth), transmittance


def sum_per_ray(values: Tensor, ray: Tensor, rays: int) -> Tensor:
    """Σ over each ray's packed samples: ``values [N, ...]`` of rays ``ray [N]`` → ``[rays, ...]``.

    Example:
        >>> sum_per_ray(torch.tensor([0.5, 0.25, 1.0]), torch.tensor([0, 0, 2]), 3).tolist()
        [0.75, 0.0, 1.0]
    """
    return values.new_zeros((rays, *values.shape[1:])).index_add(0, ray, values)


# A ray whose coloured samples weigh less than this in all is black: it would add about this
# much to its pixel, and deferred colour's network is spared the rays that carry nothing.
MIN_SHADED_WEIGHT = 1e-12


def shade_rays(accumulated: Tensor, coloured_weight: Tensor, weight: Tensor, directions: Tensor,
               shade_fn: Callable[[Tensor, Tensor], Tensor] | None = None) -> Tensor:
    """Each ray's colour ``[R, 3]`` over no background from what its coloured samples
    composited: ``accumulated [R, C]`` (Σ w·v over them) and ``coloured_weight [R]`` (Σ w). Their
    weighted mean stands for the ray's whole ``weight [R]``, the faint samples left without a
    value included: ``weight · mean`` where the values are colours (``shade_fn`` None), ``weight
    · shade_fn(mean, directions)`` where they are appearance features (deferred colour, run on
    the rays with colour alone). A ray whose coloured weight is under ``MIN_SHADED_WEIGHT`` is black.

    Example:
        >>> acc, coloured = torch.tensor([[0.25, 0.5, 0.0], [0.0, 0.0, 0.0]]), torch.tensor([0.5, 0.0])
        >>> shade_rays(acc, coloured, torch.tensor([0.75, 0.5]), torch.zeros(2, 3)).tolist()
        [[0.375, 0.75, 0.0], [0.0, 0.0, 0.0]]
        >>> shade_rays(acc, coloured, torch.tensor([0.75, 0.5]), torch.zeros(2, 3),
        ...            lambda mean, d: mean.sum(dim=1, keepdim=True).expand(-1, 3)).tolist()
        [[1.125, 1.125, 1.125], [0.0, 0.0, 0.0]]
    """
    shaded = (coloured_weight > MIN_SHADED_WEIGHT).nonzero().squeeze(1)  # as shaded_ray_count
    if shaded.numel() == 0:  # no values at all, perhaps not even their width
        return accumulated.new_zeros((accumulated.shape[0], 3))
    whole = getattr(shade_fn, "shade_rays", None)
    if whole is not None:  # the same in one pass (field_functions.ShadeFn)
        return whole(accumulated, coloured_weight, weight, directions, shaded)
    mean = accumulated.index_select(0, shaded) / coloured_weight.index_select(0, shaded)[:, None]
    colour = mean if shade_fn is None else shade_fn(mean, directions.index_select(0, shaded))
    colour = colour * weight.index_select(0, shaded)[:, None].to(colour.dtype)
    return colour.new_zeros((accumulated.shape[0], 3)).index_put((shaded,), colour)


def shaded_ray_count(coloured_weight: Tensor) -> int:
    """How many rays ``shade_rays`` runs the shading on: those with coloured weight.

    Example:
        >>> shaded_ray_count(torch.tensor([0.5, 0.0, 1e-3]))
        2
    """
    return int((coloured_weight > MIN_SHADED_WEIGHT).sum())


def composite_features_packed(density: Tensor, deltas: Tensor, t_mid: Tensor, ray: Tensor, coloured: Tensor,
                              features: Tensor, rays: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Deferred colour's compositing of samples packed per ray (``render_weights_packed``'s
    layout): each ray's opacity Σ w ``[R]``, depth Σ w·t ``[R]``, and over the ``coloured``
    samples (indices into the samples, ascending) their weight Σ w ``[R]`` and their
    ``features [C, F]`` composited, Σ w·f ``[R, F]``. The reference of the compiled pass
    (``compiled_composite.py``).

    Example:
        >>> opacity, depth, coloured, features = composite_features_packed(
        ...     torch.tensor([1e9, 1.0, 0.5]), torch.ones(3), torch.tensor([1.0, 2.0, 3.0]), torch.tensor([0, 0, 1]),
        ...     torch.tensor([0, 2]), torch.tensor([[2.0], [4.0]]), rays=2)
        >>> [round(v, 4) for v in opacity.tolist()], [round(v, 4) for v in features[:, 0].tolist()]
        ([1.0, 0.3935], [2.0, 1.5739])
    """
    weights, _ = render_weights_packed(density, deltas, ray)
    weight, coloured_ray = weights.index_select(0, coloured), ray.index_select(0, coloured)
    return (sum_per_ray(weights, ray, rays), sum_per_ray(weights * t_mid, ray, rays),
            sum_per_ray(weight, coloured_ray, rays), sum_per_ray(weight[:, None] * features, coloured_ray, rays))
