"""Where to evaluate the field along each ray.

Samples are intervals given by their edges ``t_edges [R, S+1]`` (distances along the ray);
the field is evaluated at each interval's midpoint and the interval's length is its δ.
The last interval ends at the ray's far bound, never at 1e10, so δ stays finite in any
precision; what lies beyond ``far`` is background.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class SamplingConfig:
    """Samples per ray of the coarse-to-fine NeRF (the paper's 64 + 128)."""

    coarse_samples: int = 64
    fine_samples: int = 128  # 0: no hierarchical sampling (the ablation)


def stratified_edges(
    t_near: Tensor, t_far: Tensor, num_samples: int, jitter: bool, generator: torch.Generator | None = None
) -> Tensor:
    """Edges of ``num_samples`` intervals per ray between ``t_near [R]`` and ``t_far [R]``.

    Without jitter the edges are uniform. With jitter every interior edge moves uniformly
    within half a bin either side (so edges never cross and each sample point falls at a
    random place in its stratum), the paper's stratified sampling.

    Example:
        >>> stratified_edges(torch.tensor([2.0]), torch.tensor([6.0]), 4, jitter=False).tolist()
        [[2.0, 3.0, 4.0, 5.0, 6.0]]
    """
    rays = t_near.shape[0]
    u = torch.linspace(0.0, 1.0, num_samples + 1, device=t_near.device, dtype=t_near.dtype)
    u = u.expand(rays, num_samples + 1)
    if jitter and num_samples > 1:
        noise = torch.rand(
            (rays, num_samples - 1), generator=generator, device=t_near.device, dtype=t_near.dtype
        )
        interior = u[:, 1:-1] + (noise - 0.5) / num_samples
        u = torch.cat([u[:, :1], interior, u[:, -1:]], dim=-1)
    return t_near[:, None] + (t_far - t_near)[:, None] * u


def interval_midpoints(t_edges: Tensor) -> Tensor:
    """Midpoints ``[R, S]`` of the intervals with edges ``[R, S+1]``."""
    return 0.5 * (t_edges[:, 1:] + t_edges[:, :-1])


def sample_pdf(
    t_edges: Tensor, weights: Tensor, num_samples: int, deterministic: bool,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draw ``num_samples`` distances per ray from the piecewise-constant pdf ∝ ``weights``.

    Inverse-CDF sampling (the paper's hierarchical sampling): the pdf is constant over each
    interval of ``t_edges [R, S+1]`` with mass ∝ ``weights [R, S]``. Rays whose weights are
    all zero (empty space, missed box) fall back to the uniform pdf instead of dividing by
    zero. ``deterministic`` uses evenly spaced quantiles (evaluation); otherwise uniform
    random ones (training). Returns sorted ``[R, num_samples]``; gradients do not flow.

    Example:
        >>> edges = torch.tensor([[0.0, 1.0, 2.0]])
        >>> sample_pdf(edges, torch.tensor([[0.0, 1.0]]), 2, deterministic=True).tolist()
        [[1.25, 1.75]]
    """
    weights = weights.detach()
    t_edges = t_edges.detach()
    total = weights.sum(dim=-1, keepdim=True)
    uniform = torch.full_like(weights, 1.0 / weights.shape[-1])
    # Divide by the total itself, however small: clamping it (to float's smallest normal)
    # would shrink a denormal-weighted pdf to ~0 and push every sample into the last bin.
    has_weight = total > 0
    pdf = torch.where(has_weight, weights / torch.where(has_weight, total, torch.ones_like(total)), uniform)
    cdf = torch.cumsum(pdf, dim=-1).clamp(max=1.0)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], dim=-1)  # [R, S+1]
    cdf[:, -1] = 1.0  # exact end, whatever the rounding of the sum
    rays = weights.shape[0]
    if deterministic:
        # Midpoints of N equal quantile bins: symmetric, never exactly 0 or 1.
        u = (torch.arange(num_samples, device=weights.device, dtype=weights.dtype) + 0.5) / num_samples
        u = u.expand(rays, num_samples).contiguous()
    else:
        u = torch.rand((rays, num_samples), generator=generator, device=weights.device, dtype=weights.dtype)
        u = torch.sort(u, dim=-1).values
    # Interval k contains u when cdf[k] <= u < cdf[k+1]; zero-mass intervals are skipped
    # because searchsorted(right=True) lands past every equal cdf value.
    upper = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    lower = upper - 1
    cdf_lo, cdf_hi = torch.gather(cdf, 1, lower), torch.gather(cdf, 1, upper)
    t_lo, t_hi = torch.gather(t_edges, 1, lower), torch.gather(t_edges, 1, upper)
    mass = cdf_hi - cdf_lo
    frac = torch.where(mass > 0, (u - cdf_lo) / mass.clamp_min(torch.finfo(mass.dtype).tiny), torch.zeros_like(u))
    return t_lo + frac.clamp(0.0, 1.0) * (t_hi - t_lo)


def merge_edges(t_edges: Tensor, t_new: Tensor) -> Tensor:
    """The union of interval edges ``[R, S+1]`` and new distances ``[R, N]``, sorted: the
    fine pass evaluates coarse and fine samples together, as in the paper."""
    return torch.sort(torch.cat([t_edges, t_new], dim=-1), dim=-1).values
