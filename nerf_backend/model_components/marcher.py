"""Marching rays in fixed steps through an occupancy grid, for any field (nerfacc's idea).

The caller passes functions, the marcher samples and renders: ``density_fn(points [P, 3],
directions [P, 3]) -> [P]`` (without gradients: which samples light reaches), ``field_fn(points, directions) ->
(density [P], colour [P, 3])`` (the samples that count, with gradients; one call, so a field
can share work between the two) or, for inference, ``ray_colour(points, ray) -> [P, 3]`` of
samples packed per ray (``core/field_functions.py``), plus an ``OccupancyGrid`` that says where
density can be. Nothing here knows what the field is.

Two renders share the same samples: ``render_marched`` for training (gradients, only for
samples light reaches) and ``render_marched_stopping_early`` for inference (only the spans an
occupancy "skip grid" keeps, packed per ray; a ray stops once opaque).

Example:
    >>> import torch
    >>> from nerf_backend.model_components.occupancy import OccupancyGrid
    >>> grid = OccupancyGrid(torch.full((3,), -1.0), torch.full((3,), 1.0), cells=8)
    >>> out = render_marched(
    ...     torch.tensor([[0.0, -3.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0]]),
    ...     torch.tensor([2.0]), torch.tensor([4.0]),
    ...     density_fn=lambda x, d: torch.full(x.shape[:1], 50.0),
    ...     field_fn=lambda x, d: (torch.full(x.shape[:1], 50.0), torch.zeros_like(x)),
    ...     occupancy=grid, step=0.05, steps=41, background=1.0)
    >>> round(float(out.opacity), 3), round(float(out.rgb.sum()), 3)  # a black, opaque cube
    (1.0, 0.0)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.field_functions import (FieldFn, LitPassFn, LitSamplesFn, RayColourFn, SampleDensityFn, ShadeFn,
                                    SparseColourFieldFn)
from ..core.stage_timer import count, stage
from .occupancy import OccupancyGrid
from .render_output import RenderOutput
from .samplers import interval_midpoints
from .compiled_composite import compiled_composite_features
from .volume_rendering import (accumulate, composite_features_packed, composite_rgb, expected_depth, render_weights,
                               render_weights_packed, shade_rays, shaded_ray_count, sum_per_ray)

# A ray whose transmittance has fallen below this is opaque: what it would still add is under
# 1e-4 of a pixel, so inference stops it and training evaluates no colour past that point.
OPAQUE_TRANSMITTANCE = 1e-4
# Inference marches this many of a ray's occupied spans at a time between checks for opaque
# rays (most rays stop at the first surface they meet, within a span or two), twice as many
# each round after, up to MAX_INFERENCE_SPANS: a ray still going is likely to go on (a young
# or translucent field), and each round has a fixed cost.
INFERENCE_SPANS = 2
MAX_INFERENCE_SPANS = 32
# Inference leaves the faintest samples of a ray without colour, up to this much of its
# weight in all, and gives that weight the ray's mean colour: a pixel moves by at most this
# times its colour range (2.55 8-bit levels; far less, as the skipped samples' colours are near
# the mean), and a soft surface's many faint samples cost no field evaluation.
SKIPPED_WEIGHT = 1e-2


@dataclass(frozen=True)
class RayStop:
    """Where inference stops a ray (its transmittance under ``opaque_transmittance``) and how
    much of its weight it may leave without colour (``skipped_weight``, its faintest samples,
    given its mean colour)."""

    opaque_transmittance: float = OPAQUE_TRANSMITTANCE
    skipped_weight: float = SKIPPED_WEIGHT


EXACT_STOP = RayStop()
# A draft (a march step coarser than the model's, the live view's frames before the exact one)
# stops a ray once 99 % of its light is taken and leaves up to 3 % of it without colour: its
# coarser step moves the image more than either. Lego's 10-minute model at 800×800, the resting
# view at twice the step: 1.14 M coloured samples → 0.80 M and 8.5 M density reads → 7.2 M,
# 31.30 → 31.16 dB against the exact frame (the NeRF's pixels).
DRAFT_STOP = RayStop(opaque_transmittance=1e-2, skipped_weight=3e-2)

# Training with a compiled march (its weights known before the field's pass) colours only the
# lit samples weighing at least this (or a hundredth of their ray's heaviest, if less); the rest
# take their ray's mean colour. On lego at 800×800 after 600 s, 1 in 3 lit samples weighed that
# much and the rest 3.6e-4 of a ray in all: the colour network's pass and its backward shrink 3x.
TRAIN_COLOURED_WEIGHT = 1e-4
TRAIN_RELATIVE_WEIGHT = 1e-2
# bench-step's count of the rays whose field pass was a field's lit pass (``_render_lit_pass``):
# the density was read by the march, not again in the "field" stage.
COMPILED_LIT_PASS = "compiled lit pass"
# bench-step's count of the rays deferred colour shaded in training (the network's work in the
# "composite" stage).
SHADED_RAYS = "shaded rays"


def march_edges(t_near: Tensor, t_far: Tensor, step: float, offset: Tensor, first: int, count: int) -> Tensor:
    """Edges ``[R, count+1]`` of march steps ``first .. first+count`` of each ray: fixed
    steps of ``step`` from ``t_near`` (the first shortened by ``offset [R, 1]`` of a step),
    cut at ``t_far``.

    Example:
        >>> march_edges(torch.tensor([1.0]), torch.tensor([1.25]), 0.1, torch.zeros(1, 1), 0, 3).tolist()
        [[1.0, 1.0, 1.100000023841858, 1.2000000476837158]]
    """
    steps = torch.arange(first, first + count + 1, device=t_near.device, dtype=t_near.dtype)
    return edge_at(steps[None, :], t_near[:, None], t_far[:, None], step, offset)


def edge_at(edge: Tensor, t_near: Tensor, t_far: Tensor, step: float, offset: Tensor) -> Tensor:
    """Where march edge number ``edge`` (a float tensor) lies along its ray: ``t_near`` plus
    ``edge - 1 + offset`` steps (edge 0 and 1 both at ``t_near`` when ``offset`` is 0), cut at
    ``t_far``; the arguments broadcast. ``march_edges`` and ``lit_intervals`` both place edges here."""
    return torch.minimum(t_near + (edge - 1.0 + offset).clamp_min(0.0) * step, t_far)


# The helpers gather samples by flat index (one nonzero() per mask), which on the CPU costs
# far less than boolean-mask indexing repeated per tensor.
def occupied_samples(occupancy: OccupancyGrid, positions: Tensor, deltas: Tensor) -> Tensor:
    """Flat indices of the samples ``positions [R, S, 3]`` that have a length and lie in
    occupied cells."""
    index = (deltas > 0).view(-1).nonzero().squeeze(1)
    return index[occupancy.query(positions.view(-1, 3).index_select(0, index))]


def density_at(density_fn: SampleDensityFn, positions: Tensor, directions: Tensor, index: Tensor,
               shape: torch.Size) -> Tensor:
    """Density ``shape = [R, S]`` at the samples ``index`` (0 elsewhere) of rays along ``directions [R, 3]``."""
    values = density_fn(positions.view(-1, 3).index_select(0, index), directions.index_select(0, index // shape[1]))
    return values.new_zeros(shape.numel()).index_put((index,), values).view(shape)


@torch.no_grad()
def lit_samples(density_fn: SampleDensityFn, positions: Tensor, directions: Tensor, deltas: Tensor,
                index: Tensor) -> Tensor:
    """Of the samples ``index``, those that light still reaches (transmittance above
    ``OPAQUE_TRANSMITTANCE``), found in a pass without gradients: what lies behind an opaque
    surface adds under 1e-4 to the pixel, so training spends no backward pass on it
    (nerfacc's early stop), however solid the object."""
    density = density_at(density_fn, positions, directions, index, deltas.shape)
    _, transmittance = render_weights(density, deltas)
    return index[transmittance.view(-1).index_select(0, index) > OPAQUE_TRANSMITTANCE]


def render_marched(
    origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor, *, density_fn: SampleDensityFn,
    field_fn: FieldFn | SparseColourFieldFn, occupancy: OccupancyGrid, step: float, steps: int,
    background: Tensor | float,
    offset: Tensor | None = None, lit_fn: LitSamplesFn | None = None, shade_fn: ShadeFn | None = None,
    lit_pass_fn: LitPassFn | None = None,
) -> RenderOutput:
    """Render rays marched in ``steps`` fixed steps of ``step`` from ``t_near`` (cut at
    ``t_far``), with gradients through ``field_fn``. ``lit_fn``, where given, finds the samples
    that count in one pass of its own (the compiled march of the grid field on the CPU) instead
    of the tensors of every step below, and the rest works on those samples alone, packed per
    ray (``_render_lit``); its output then has no per-step ``weights`` or ``t_edges``. With
    ``shade_fn`` (deferred colour), ``field_fn``'s second output is appearance features, and
    each ray's composited features are shaded once (``shade_rays``); with ``lit_pass_fn`` too
    (``lit_fn`` then gives each sample's record), the field's pass and the compositing are that
    one call (the grid field's compiled lit pass).

    Samples in empty cells are dropped, then those hidden behind opaque ones (found with
    ``density_fn``, without gradients: it may be a cheaper form of the same density); only
    the rest go through ``field_fn``, colour included, however little they weigh.
    ``offset [R, 1]`` in [0, 1) shortens each ray's first step (random in training:
    unbiased, and every step still covered).

    Why not skip samples of low *weight* in training: a young field's samples all weigh
    little, so none would get a colour, each would count as black, and every bright pixel
    would push density down: a large white object then trains to empty space. (Inference
    leaves only a bounded share of a trained field's weight uncoloured.)
    """
    if offset is None:
        offset = origins.new_zeros((origins.shape[0], 1))
    if lit_fn is not None:
        if lit_pass_fn is not None:
            return _render_lit_pass(origins, directions, t_near, t_far, lit_fn, lit_pass_fn, steps, background,
                                    offset, shade_fn)
        return _render_lit(origins, directions, t_near, t_far, field_fn, lit_fn, step, steps, background, offset,
                           shade_fn)
    with stage("march", items=origins.shape[0] * steps):
        t_edges = march_edges(t_near, t_far, step, offset, 0, steps)
        deltas = t_edges[:, 1:] - t_edges[:, :-1]
        t_mid = interval_midpoints(t_edges)
        positions = origins[:, None, :] + directions[:, None, :] * t_mid[..., None]
        occupied = occupied_samples(occupancy, positions, deltas)
    with stage("density pass", items=occupied.numel()):
        lit = lit_samples(density_fn, positions, directions, deltas, occupied)
    with stage("field", items=lit.numel()):
        density_values, colour_values = field_fn(positions.view(-1, 3).index_select(0, lit),
                                                 directions.index_select(0, lit // deltas.shape[1]))
    with stage("composite", items=lit.numel()):
        density = density_values.new_zeros(deltas.numel()).index_put((lit,), density_values).view(deltas.shape)
        weights, _ = render_weights(density, deltas)
        values = colour_values.new_zeros((deltas.numel(), colour_values.shape[1])).index_put((lit,), colour_values)
        values = values.view(*deltas.shape, -1)
        opacity = weights.sum(dim=-1)
        if shade_fn is None:
            rgb = composite_rgb(weights, values, background)
        else:
            rgb = (shade_rays(accumulate(weights, values), opacity, opacity, directions, shade_fn)
                   + (1.0 - opacity)[:, None] * background)
        return RenderOutput(rgb=rgb, depth=expected_depth(weights, t_mid), opacity=opacity, weights=weights,
                            t_edges=t_edges, field_samples=lit.numel())


def lit_intervals(lit: Tensor, t_near: Tensor, t_far: Tensor, step: float, steps: int,
                  offset: Tensor) -> tuple[Tensor, Tensor]:
    """The start and end along its ray of each packed march interval ``lit [N]`` (flat indices
    ``ray · steps + u``): ``march_edges``' edges ``u`` and ``u + 1`` (``edge_at``), for the
    samples alone.

    Example:
        >>> lo, hi = lit_intervals(torch.tensor([1, 2]), torch.tensor([1.0]), torch.tensor([1.25]), 0.1, 3,
        ...                        torch.zeros(1, 1))
        >>> lo.tolist(), hi.tolist()  # march_edges: [1.0, 1.0, 1.1, 1.2]
        ([1.0, 1.100000023841858], [1.100000023841858, 1.2000000476837158])
    """
    ray, u = lit // steps, (lit % steps).to(t_near.dtype)
    near, far, shift = t_near.index_select(0, ray), t_far.index_select(0, ray), offset[:, 0].index_select(0, ray)
    return edge_at(u, near, far, step, shift), edge_at(u + 1.0, near, far, step, shift)


def _render_lit(origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
                field_fn: SparseColourFieldFn, lit_fn: LitSamplesFn, step: float, steps: int,
                background: Tensor | float, offset: Tensor, shade_fn: ShadeFn | None) -> RenderOutput:
    """``render_marched`` where ``lit_fn`` finds the lit samples: everything after it packed per
    ray, over those samples alone. The march's other steps hold no density, so the image is the
    one the ``[R, S]`` tensors of every step give (tests/test_compiled_grid.py,
    test_volume_rendering.py). On lego at 800×800 a step of 2 048 rays marches 553 k steps and
    lights 29 k samples: packed, the compositing took 2.4-2.9 ms a step against 7.9-8.9 over
    every step, its backward 16-18 ms against 22-24, the whole step 41-46 ms against 56-62
    (bench-step, before and after in turn, AVX-512, 2 threads)."""
    rays = origins.shape[0]
    with stage("march", items=rays * steps):
        lit, lit_weight = lit_fn(origins, directions, t_near, t_far, offset)
        ray = lit // steps
        low, high = lit_intervals(lit, t_near, t_far, step, steps, offset)
        deltas, t_mid = high - low, 0.5 * (high + low)
        lit_positions = origins.index_select(0, ray) + directions.index_select(0, ray) * t_mid[:, None]
        coloured = colour_worthy(lit_weight, ray, rays)
        count("coloured samples", coloured.numel())
    with stage("field", items=lit.numel()):
        density_values, colour_values = field_fn(lit_positions, directions.index_select(0, ray), coloured)
    with stage("composite", items=lit.numel()):
        if shade_fn is None:
            weights, _ = render_weights_packed(density_values, deltas, ray)
            opacity = sum_per_ray(weights, ray, rays)
            colours = _packed_colours(coloured, colour_values.to(weights.dtype), weights, ray, rays)
            rgb, depth = sum_per_ray(weights[:, None] * colours, ray, rays), sum_per_ray(weights * t_mid, ray, rays)
        else:  # the features of the coloured samples composited, their mean shaded once a ray
            inputs = (density_values, deltas, t_mid, ray, coloured, colour_values, rays)
            composited = compiled_composite_features(*inputs)
            if composited is None:  # not on the CPU in float32, or no C compiler
                composited = composite_features_packed(*inputs)
            opacity, depth, coloured_weight, accumulated = composited
            rgb = shade_rays(accumulated, coloured_weight, opacity, directions, shade_fn)
        rgb = rgb + (1.0 - opacity)[:, None] * background
    if shade_fn is not None:
        count(SHADED_RAYS, lambda: shaded_ray_count(coloured_weight))
    return RenderOutput(rgb=rgb, depth=depth, opacity=opacity, weights=None, t_edges=None, field_samples=lit.numel())


def _render_lit_pass(origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor, lit_fn: LitSamplesFn,
                     lit_pass_fn: LitPassFn, steps: int, background: Tensor | float, offset: Tensor,
                     shade_fn: ShadeFn) -> RenderOutput:
    """``_render_lit`` with deferred colour where the field's pass over the lit samples and the
    compositing are one call (``lit_pass_fn``), from the march's record of each sample: the
    same image and gradients (tests/test_compiled_lit_pass.py)."""
    if shade_fn is None:
        raise ValueError("a field's lit pass composites appearance features: it needs the field's shade_fn")
    rays = origins.shape[0]
    with stage("march", items=rays * steps):
        lit, lit_weight, record = lit_fn(origins, directions, t_near, t_far, offset)
    with stage("field", items=lit.numel()):
        opacity, depth, coloured_weight, accumulated, coloured = lit_pass_fn(lit, lit_weight, record, rays, steps)
        count("coloured samples", coloured)
        count(COMPILED_LIT_PASS, rays)
    with stage("composite", items=lit.numel()):
        rgb = shade_rays(accumulated, coloured_weight, opacity, directions, shade_fn)
        rgb = rgb + (1.0 - opacity)[:, None] * background
    count(SHADED_RAYS, lambda: shaded_ray_count(coloured_weight))
    return RenderOutput(rgb=rgb, depth=depth, opacity=opacity, weights=None, t_edges=None, field_samples=lit.numel())


def _packed_colours(coloured: Tensor, colours: Tensor, weights: Tensor, ray: Tensor, rays: int) -> Tensor:
    """Each packed lit sample's colour ``[N, 3]``: the field's at the ``coloured`` ones (indices
    into the samples), the weighted mean of its ray's coloured samples (without gradients) at
    the others."""
    full = colours.new_zeros((weights.numel(), 3)).index_put((coloured,), colours)
    left = torch.ones_like(ray, dtype=torch.bool).index_fill_(0, coloured, False).nonzero().squeeze(1)
    if left.numel() == 0:
        return full
    with torch.no_grad():
        weight, coloured_ray = weights.index_select(0, coloured), ray.index_select(0, coloured)
        total = sum_per_ray(weight[:, None] * colours, coloured_ray, rays)
        mean = total / sum_per_ray(weight, coloured_ray, rays).clamp_min(1e-30)[:, None]
    return full.index_put((left,), mean.index_select(0, ray.index_select(0, left)))


def colour_worthy(weight: Tensor, ray: Tensor, rays: int) -> Tensor:
    """Which of a training march's lit samples (their weights without gradients, ``weight [L]``,
    of rays ``ray [L]``) get a colour: those weighing at least ``TRAIN_COLOURED_WEIGHT``, or, on
    a ray whose heaviest sample weighs less than 100 times that, at least a hundredth of it (a
    young field's faint rays colour nearly all their samples, never none). Indices into ``weight``.

    Example:
        >>> colour_worthy(torch.tensor([0.5, 1e-6, 0.3, 2e-7, 1e-6]), torch.tensor([0, 0, 0, 1, 1]), 2).tolist()
        [0, 2, 3, 4]
    """
    heaviest = weight.new_zeros(rays).scatter_reduce(0, ray, weight, "amax", include_self=False)
    threshold = torch.clamp(heaviest.index_select(0, ray) * TRAIN_RELATIVE_WEIGHT, max=TRAIN_COLOURED_WEIGHT)
    return (weight >= threshold).nonzero().squeeze(1)


class RayValues:
    """A sum per ray of values whose width (colours, or a field's appearance features) is known
    at the first ``add``; no values yet reads as zero colours. ``whole_rays``: the caller's
    promise that each ray's samples all come in one call of ``add_weighted``; then a fused pass
    sets each reached ray's row rather than adding to a zeroed one, and the rows of rays no
    sample reaches hold nothing defined (they have no coloured weight: ``shade_rays`` leaves
    them black without reading them)."""

    def __init__(self, like: Tensor, rays: int, whole_rays: bool = False) -> None:
        self._like, self.rays, self.whole_rays = like, rays, whole_rays
        self._values: Tensor | None = None

    def add(self, ray: Tensor, values: Tensor) -> None:
        """Add ``values [N, C]`` to rays ``ray [N]``."""
        if self._values is None:
            self._values = values.new_zeros((self.rays, values.shape[1]))
        self._values.index_add_(0, ray, values)

    def add_weighted(self, ray_colour: RayColourFn, x: Tensor, ray: Tensor, weight: Tensor) -> None:
        """Add ``weight · ray_colour(x, ray)`` to rays ``ray [N]`` (ascending), in the function's
        own fused pass where it has one (``composite(x, ray, weight, out, fresh)`` and
        ``channels``: ``compiled_colour.CompiledRayFeatures``)."""
        fused = getattr(ray_colour, "composite", None)
        if fused is None:
            self.add(ray, weight[:, None] * ray_colour(x, ray).to(weight.dtype))
            return
        if self._values is None:
            shape = (self.rays, ray_colour.channels)
            self._values = (x.new_empty if self.whole_rays else x.new_zeros)(shape, dtype=torch.float32)
        fused(x, ray, weight, self._values, fresh=self.whole_rays)

    @property
    def values(self) -> Tensor:
        return self._values if self._values is not None else self._like.new_zeros((self.rays, 3))


def occupied_spans(occupancy: OccupancyGrid, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
                   step: float, steps: int) -> tuple[Tensor, Tensor, int]:
    """The spans of each ray that may hold density, packed: ``ray [N]`` and the first march
    interval ``first [N]`` of each span (sorted by ray, then along it), and the intervals a
    span holds. One query of ``occupancy.skip_cells()`` a span replaces ``span`` fine queries,
    and spans in empty space are never marched at all.

    Interval ``u`` of a ray is ``[t_near + u·step, t_near + (u+1)·step]`` cut at ``t_far``,
    ``u < steps - 1``: ``march_edges``' intervals without its first, empty one.

    Example:
        >>> grid = OccupancyGrid(torch.full((3,), -1.0), torch.full((3,), 1.0), cells=32)
        >>> _ = grid.occupied.zero_()
        >>> grid.occupied[24:, 16, 16] = True  # a line of cells from x = 0.5 to 1
        >>> ray, first, span = occupied_spans(grid, torch.tensor([[-3.0, 0.01, 0.01]]),
        ...                                   torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([2.0]),
        ...                                   torch.tensor([4.0]), step=1 / 16, steps=33)
        >>> span, first.tolist()  # the spans whose midpoints lie within 6 cells of the line
        (12, [12, 24])
    """
    span = occupancy.skip_span_steps(step)
    spans = -(-(steps - 1) // span)
    hit = (t_far > t_near).nonzero().squeeze(1)
    first = torch.arange(spans, device=origins.device) * span
    span_start = first.to(origins.dtype) * step  # from t_near
    ray_near = t_near.index_select(0, hit)[:, None]
    midpoints = ray_near + (span_start + 0.5 * span * step)[None, :]
    marked = occupancy.occupied_along(origins.index_select(0, hit), directions.index_select(0, hit), midpoints,
                                      skip=True)
    marked &= span_start[None, :] < t_far.index_select(0, hit)[:, None] - ray_near
    ray_local, span_index = marked.nonzero().unbind(1)
    return hit.index_select(0, ray_local), first.index_select(0, span_index), span


@torch.no_grad()
def render_marched_stopping_early(
    origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor, *, density_fn: SampleDensityFn,
    ray_colour: RayColourFn, occupancy: OccupancyGrid, step: float, steps: int, background: Tensor | float,
    stop: RayStop = EXACT_STOP, shade_fn: ShadeFn | None = None,
) -> RenderOutput:
    """``render_marched``'s image without gradients, over the same fixed steps, marched only
    where the occupancy grid allows and stopped once a ray is opaque (``stop``'s).

    The rays' spans that may hold density are found first (``occupied_spans``, one coarse
    query a span); then each ray marches ``INFERENCE_SPANS`` of its spans in fine steps, twice
    as many each round after, and a ray stops once its transmittance is below
    ``stop.opaque_transmittance`` (exact: what it would still add is under 1e-4 of a pixel).
    Empty space and what lies behind a surface cost nothing; world positions are made only for
    samples in occupied cells. With ``shade_fn`` (deferred colour), ``ray_colour`` gives the
    samples' appearance features, composited and shaded once a ray (``shade_rays``)."""
    rays = origins.shape[0]
    transmittance = origins.new_ones(rays)
    composited = RayValues(origins, rays)  # Σ w·colour (or features) of the coloured samples, per ray
    depth = origins.new_zeros(rays)
    skipped = origins.new_zeros(rays)  # weight left without colour, per ray
    coloured_weight = origins.new_zeros(rays)  # weight with colour, per ray
    with stage("spans", items=rays):
        span_ray, span_first, span = occupied_spans(occupancy, origins, directions, t_near, t_far, step, steps)
    counts = torch.bincount(span_ray, minlength=rays)
    offsets = torch.cumsum(counts, 0) - counts
    active = counts.nonzero().squeeze(1)
    in_span = torch.arange(span, device=origins.device)
    taken, width = 0, INFERENCE_SPANS
    while active.numel() > 0:
        in_round = torch.arange(width, device=origins.device)
        ray_counts = counts.index_select(0, active)
        with stage("march", items=len(active) * width * span):
            slot_valid = (taken + in_round)[None, :] < ray_counts[:, None]  # [A, B]
            slot = (offsets.index_select(0, active)[:, None] + taken + in_round).clamp_max(span_ray.numel() - 1)
            interval = (span_first[slot][:, :, None] + in_span).view(len(active), -1)  # [A, B·span]
            valid = slot_valid[:, :, None].expand(-1, -1, span).reshape(len(active), -1) & (interval < steps - 1)
            ray_near, ray_far = t_near.index_select(0, active)[:, None], t_far.index_select(0, active)[:, None]
            t_lo = torch.minimum(ray_near + interval * step, ray_far)
            deltas = (torch.minimum(t_lo + step, ray_far) - t_lo) * valid
            t_mid = t_lo + 0.5 * deltas
            ray_origins, ray_directions = origins.index_select(0, active), directions.index_select(0, active)
            occupied = occupancy.occupied_along(ray_origins, ray_directions, t_mid) & (deltas > 0)
            index = occupied.view(-1).nonzero().squeeze(1)
            samples = deltas.shape[1]
            sample_ray = index // samples
            positions = torch.addcmul(ray_origins.index_select(0, sample_ray),
                                      ray_directions.index_select(0, sample_ray),
                                      t_mid.view(-1).index_select(0, index)[:, None])
        with stage("density", items=index.numel()):
            sample_density = density_fn(positions, ray_directions.index_select(0, sample_ray))
            density = deltas.new_zeros(deltas.numel()).index_put_((index,), sample_density).view(deltas.shape)
        round_weights, round_transmittance = render_weights(density, deltas)
        entering = transmittance.index_select(0, active)
        weights = round_weights * entering[:, None]
        # Colour where light still reaches (beyond the stop's transmittance), of the samples with
        # density, but for the faintest: up to the stop's skipped weight of each ray's weight is
        # left without colour and given its other samples' mean colour at the end.
        lit = (density > 0) & ((round_transmittance * entering[:, None]) > stop.opaque_transmittance)
        faint = lit & (weights < stop.skipped_weight)
        faint_sum = torch.cumsum(weights * faint, dim=1) + skipped.index_select(0, active)[:, None]
        coloured = lit & ~(faint & (faint_sum <= stop.skipped_weight))
        skipped.index_add_(0, active, (weights * (lit & ~coloured)).sum(dim=1))
        coloured_weight.index_add_(0, active, (weights * coloured).sum(dim=1))
        wanted = coloured.view(-1).index_select(0, index)
        with stage("colour", items=wanted.sum()):
            colour = ray_colour(positions[wanted], active.index_select(0, sample_ray[wanted]))
        composited.add(active, accumulate(weights * coloured, colour.new_zeros(
            (deltas.numel(), colour.shape[1])).index_put_((index[wanted],), colour).view(*deltas.shape, -1)))
        depth.index_add_(0, active, expected_depth(weights, t_mid))
        leaving = entering * round_transmittance[:, -1] * torch.exp(-density[:, -1] * deltas[:, -1])
        transmittance[active] = leaving
        taken += width
        width = min(2 * width, MAX_INFERENCE_SPANS)
        active = active[(leaving > stop.opaque_transmittance) & (ray_counts > taken)]
    # The skipped weight takes the coloured samples' weighted mean colour (a ratio of sums of
    # the same weights, so within the colours' range); a ray with none keeps it black.
    rgb = shade_rays(composited.values, coloured_weight, coloured_weight + skipped, directions, shade_fn)
    opacity = 1.0 - transmittance
    return RenderOutput(rgb=rgb + transmittance[:, None] * background, depth=depth, opacity=opacity,
                        weights=None, t_edges=None)
