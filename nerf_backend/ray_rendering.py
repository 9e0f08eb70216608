"""Coarse-to-fine rendering of a batch of rays with a pair of fields (the paper's Sec. 5.2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .fields import NerfField
from .samplers import interval_midpoints, merge_edges, sample_pdf, stratified_edges
from .volume_rendering import composite_rgb, expected_depth, render_weights


@dataclass(frozen=True)
class SamplingConfig:
    coarse_samples: int = 64
    fine_samples: int = 128  # 0: no hierarchical sampling (the ablation)


@dataclass
class RenderOutput:
    """What one pass renders for each ray."""

    rgb: Tensor  # [R, 3], composited over the background
    depth: Tensor  # [R], expected distance along the ray (0 where empty)
    opacity: Tensor  # [R], 1 - final transmittance
    weights: Tensor  # [R, S]
    t_edges: Tensor  # [R, S+1]


def render_pass(
    field: NerfField, origins: Tensor, directions: Tensor, t_edges: Tensor, background: Tensor | float
) -> RenderOutput:
    """Evaluate ``field`` at the midpoints of the intervals ``t_edges`` and integrate."""
    t_mid = interval_midpoints(t_edges)
    rays, samples = t_mid.shape
    positions = origins[:, None, :] + directions[:, None, :] * t_mid[..., None]
    view_dirs = directions[:, None, :].expand(rays, samples, 3)
    density, rgb = field(positions.reshape(-1, 3), view_dirs.reshape(-1, 3))
    deltas = t_edges[:, 1:] - t_edges[:, :-1]
    weights, _ = render_weights(density.reshape(rays, samples), deltas)
    rgb = rgb.reshape(rays, samples, 3)
    return RenderOutput(
        rgb=composite_rgb(weights, rgb, background),
        depth=expected_depth(weights, t_mid),
        opacity=weights.sum(dim=-1),
        weights=weights,
        t_edges=t_edges,
    )


def render_rays(
    coarse: NerfField,
    fine: NerfField | None,
    origins: Tensor,
    directions: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    sampling: SamplingConfig,
    background: Tensor | float,
    training: bool,
    generator: torch.Generator | None = None,
) -> tuple[RenderOutput, RenderOutput | None]:
    """Render rays coarse then fine: stratified samples for the coarse field, then the fine
    field at the union of those and ``fine_samples`` drawn from the coarse weights.

    Returns ``(coarse_output, fine_output)``; the fine output is None without a fine field.
    Jitter and random quantiles are used only when ``training``, so evaluation is
    deterministic.
    """
    coarse_edges = stratified_edges(t_near, t_far, sampling.coarse_samples, jitter=training, generator=generator)
    coarse_out = render_pass(coarse, origins, directions, coarse_edges, background)
    if fine is None or sampling.fine_samples == 0:
        return coarse_out, None
    t_new = sample_pdf(
        coarse_edges, coarse_out.weights, sampling.fine_samples, deterministic=not training, generator=generator
    )
    fine_out = render_pass(fine, origins, directions, merge_edges(coarse_edges, t_new), background)
    return coarse_out, fine_out
