"""Marching rays in fixed steps through an occupancy grid, for any field (nerfacc's idea).

The caller passes functions, the marcher samples and renders: ``density_fn(points [P, 3]) ->
[P]`` (without gradients: which samples light reaches), ``field_fn(points, directions) ->
(density [P], colour [P, 3])`` (the samples that count, with gradients; one call, so a field
can share work between the two) or ``colour_fn(points, directions) -> [P, 3]``, plus an
``OccupancyGrid`` that says where density can be. Nothing here knows what the field is.

Two renders share the same samples: ``render_marched`` for training (gradients, only for
samples light reaches) and ``render_marched_stopping_early`` for inference (segments of
steps; a ray stops once opaque).

Example:
    >>> import torch
    >>> from nerf_backend.model_components.occupancy import OccupancyGrid
    >>> grid = OccupancyGrid(torch.full((3,), -1.0), torch.full((3,), 1.0), cells=8)
    >>> out = render_marched(
    ...     torch.tensor([[0.0, -3.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0]]),
    ...     torch.tensor([2.0]), torch.tensor([4.0]),
    ...     density_fn=lambda x: torch.full(x.shape[:1], 50.0),
    ...     field_fn=lambda x, d: (torch.full(x.shape[:1], 50.0), torch.zeros_like(x)),
    ...     occupancy=grid, step=0.05, steps=41, background=1.0)
    >>> round(float(out.opacity), 3), round(float(out.rgb.sum()), 3)  # a black, opaque cube
    (1.0, 0.0)
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from .occupancy import OccupancyGrid
from .render_output import RenderOutput
from .samplers import interval_midpoints
from .volume_rendering import accumulate, composite_rgb, expected_depth, render_weights

DensityFn = Callable[[Tensor], Tensor]
ColourFn = Callable[[Tensor, Tensor], Tensor]
FieldFn = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]

# A ray whose transmittance has fallen below this is opaque: what it would still add is under
# 1e-4 of a pixel, so inference stops it and training evaluates no colour past that point.
OPAQUE_TRANSMITTANCE = 1e-4
# Inference marches this many steps at a time between checks for opaque rays.
INFERENCE_SEGMENT = 32


def march_edges(t_near: Tensor, t_far: Tensor, step: float, offset: Tensor, first: int, count: int) -> Tensor:
    """Edges ``[R, count+1]`` of march steps ``first .. first+count`` of each ray: fixed
    steps of ``step`` from ``t_near`` (the first shortened by ``offset [R, 1]`` of a step),
    cut at ``t_far``.

    Example:
        >>> march_edges(torch.tensor([1.0]), torch.tensor([1.25]), 0.1, torch.zeros(1, 1), 0, 3).tolist()
        [[1.0, 1.0, 1.100000023841858, 1.2000000476837158]]
    """
    steps = torch.arange(first, first + count + 1, device=t_near.device, dtype=t_near.dtype)
    t_edges = t_near[:, None] + (steps[None, :] - 1.0 + offset).clamp_min(0.0) * step
    return torch.minimum(t_edges, t_far[:, None])


# The helpers gather samples by flat index (one nonzero() per mask), which on the CPU costs
# far less than boolean-mask indexing repeated per tensor.
def occupied_samples(occupancy: OccupancyGrid, positions: Tensor, deltas: Tensor) -> Tensor:
    """Flat indices of the samples ``positions [R, S, 3]`` that have a length and lie in
    occupied cells."""
    index = (deltas > 0).view(-1).nonzero().squeeze(1)
    return index[occupancy.query(positions.view(-1, 3).index_select(0, index))]


def density_at(density_fn: DensityFn, positions: Tensor, index: Tensor, shape: torch.Size) -> Tensor:
    """Density ``shape = [R, S]`` at the samples ``index`` (0 elsewhere)."""
    values = density_fn(positions.view(-1, 3).index_select(0, index))
    return values.new_zeros(shape.numel()).index_put((index,), values).view(shape)


@torch.no_grad()
def lit_samples(density_fn: DensityFn, positions: Tensor, deltas: Tensor, index: Tensor) -> Tensor:
    """Of the samples ``index``, those that light still reaches (transmittance above
    ``OPAQUE_TRANSMITTANCE``), found in a pass without gradients: what lies behind an opaque
    surface adds under 1e-4 to the pixel, so training spends no backward pass on it
    (nerfacc's early stop), however solid the object."""
    density = density_at(density_fn, positions, index, deltas.shape)
    _, transmittance = render_weights(density, deltas)
    return index[transmittance.view(-1).index_select(0, index) > OPAQUE_TRANSMITTANCE]


def colour_where_visible(colour_fn: ColourFn, positions: Tensor, directions: Tensor, density: Tensor,
                         transmittance: Tensor) -> Tensor:
    """Colour ``[R, S, 3]``, evaluated only for samples with density that light still
    reaches (transmittance above ``OPAQUE_TRANSMITTANCE``): everything skipped behind that
    point adds less than ``OPAQUE_TRANSMITTANCE`` to the pixel, whatever its colour.

    Why not skip samples of low *weight* instead: a young field's samples all weigh little,
    so none would get a colour, each would count as black, and every bright pixel would push
    density down: a large white object then trains to empty space."""
    samples = density.shape[1]
    visible = (density.detach() > 0) & (transmittance.detach() > OPAQUE_TRANSMITTANCE)
    index = visible.view(-1).nonzero().squeeze(1)
    colour = colour_fn(positions.view(-1, 3).index_select(0, index), directions.index_select(0, index // samples))
    return positions.new_zeros((positions.shape[0] * samples, 3)).index_put((index,), colour).view(positions.shape)


def render_marched(
    origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor, *, density_fn: DensityFn,
    field_fn: FieldFn, occupancy: OccupancyGrid, step: float, steps: int, background: Tensor | float,
    offset: Tensor | None = None,
) -> RenderOutput:
    """Render rays marched in ``steps`` fixed steps of ``step`` from ``t_near`` (cut at
    ``t_far``), with gradients through ``field_fn``.

    Samples in empty cells are dropped, then those hidden behind opaque ones (found with
    ``density_fn``, without gradients: it may be a cheaper form of the same density); only
    the rest go through ``field_fn``. ``offset [R, 1]`` in [0, 1) shortens each ray's first
    step (random in training: unbiased, and every step still covered).
    """
    if offset is None:
        offset = origins.new_zeros((origins.shape[0], 1))
    t_edges = march_edges(t_near, t_far, step, offset, 0, steps)
    deltas = t_edges[:, 1:] - t_edges[:, :-1]
    t_mid = interval_midpoints(t_edges)
    positions = origins[:, None, :] + directions[:, None, :] * t_mid[..., None]
    lit = lit_samples(density_fn, positions, deltas, occupied_samples(occupancy, positions, deltas))
    density_values, colour_values = field_fn(positions.view(-1, 3).index_select(0, lit),
                                             directions.index_select(0, lit // deltas.shape[1]))
    density = density_values.new_zeros(deltas.numel()).index_put((lit,), density_values).view(deltas.shape)
    rgb = colour_values.new_zeros((deltas.numel(), 3)).index_put((lit,), colour_values).view(positions.shape)
    weights, _ = render_weights(density, deltas)
    return RenderOutput(rgb=composite_rgb(weights, rgb, background), depth=expected_depth(weights, t_mid),
                        opacity=weights.sum(dim=-1), weights=weights, t_edges=t_edges)


@torch.no_grad()
def render_marched_stopping_early(
    origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor, *, density_fn: DensityFn,
    colour_fn: ColourFn, occupancy: OccupancyGrid, step: float, steps: int, background: Tensor | float,
) -> RenderOutput:
    """``render_marched``'s image without gradients, marched ``INFERENCE_SEGMENT`` steps at
    a time; a ray stops once opaque (transmittance below ``OPAQUE_TRANSMITTANCE``), so
    surfaces hide what lies behind them from the cost as well as from the image."""
    rays = origins.shape[0]
    transmittance = origins.new_ones(rays)
    rgb = origins.new_zeros((rays, 3))
    depth = origins.new_zeros(rays)
    active = torch.arange(rays, device=origins.device)
    for first in range(0, steps, INFERENCE_SEGMENT):
        count = min(INFERENCE_SEGMENT, steps - first)
        ray_origins, ray_directions, ray_far = origins[active], directions[active], t_far[active]
        t_edges = march_edges(t_near[active], ray_far, step, origins.new_zeros((len(active), 1)), first, count)
        deltas = t_edges[:, 1:] - t_edges[:, :-1]
        t_mid = interval_midpoints(t_edges)
        positions = ray_origins[:, None, :] + ray_directions[:, None, :] * t_mid[..., None]
        density = density_at(density_fn, positions, occupied_samples(occupancy, positions, deltas), deltas.shape)
        segment_weights, segment_transmittance = render_weights(density, deltas)
        entering = transmittance[active]
        weights = segment_weights * entering[:, None]
        colour = colour_where_visible(colour_fn, positions, ray_directions, density,
                                      segment_transmittance * entering[:, None])
        rgb.index_add_(0, active, accumulate(weights, colour))
        depth.index_add_(0, active, expected_depth(weights, t_mid))
        leaving = entering * segment_transmittance[:, -1] * torch.exp(-density[:, -1] * deltas[:, -1])
        transmittance[active] = leaving
        active = active[(leaving > OPAQUE_TRANSMITTANCE) & (t_edges[:, -1] < ray_far)]
        if active.numel() == 0:
            break
    return RenderOutput(rgb=rgb + transmittance[:, None] * background, depth=depth, opacity=1.0 - transmittance,
                        weights=None, t_edges=None)
