"""Models: a field (or two) plus the way rays are sampled through it.

Every model renders a batch of rays with ``forward(origins, directions, t_near, t_far,
background, generator) -> list[RenderOutput]``; the training loss sums the squared error
of every output (the paper's coarse + fine) and the last output is the image. The trainer
calls ``before_step(iteration)`` so a model can maintain its own state (occupancy).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from .config import TrainConfig
from .dataset import SceneBounds
from .fields import NerfField
from .grid_encodings import Vertices
from .grid_field import GridField
from .occupancy import OccupancyGrid
from .occupancy_prior import OccupancyPrior
from .ray_rendering import RenderOutput, render_rays
from .samplers import interval_midpoints
from .volume_rendering import accumulate, composite_rgb, expected_depth, render_weights


class NerfModel(nn.Module):
    """The paper's model: coarse field + (optional) fine field, rendered coarse-to-fine."""

    def __init__(self, config: TrainConfig) -> None:
        super().__init__()
        self.config = config
        self.coarse = NerfField(config.field)
        self.fine = NerfField(config.field) if config.sampling.fine_samples > 0 else None

    def before_step(self, iteration: int) -> bool:
        return False

    def match_state(self, state: dict) -> None:
        pass

    def forward(
        self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
        background: Tensor | float = 1.0, generator: torch.Generator | None = None,
    ) -> list[RenderOutput]:
        coarse, fine = render_rays(
            self.coarse, self.fine, origins, directions, t_near, t_far,
            self.config.sampling, background, training=self.training, generator=generator,
        )
        return [coarse] if fine is None else [coarse, fine]


# Rays per inference pass of the grid model: it holds one segment of samples per ray, so
# large chunks stay small in memory and amortise per-call overhead. Measured on 2 CPU cores,
# the fast preset rendering an 800×800 view: 1024 rays a chunk ~11-13 s, 4096 ~10 s,
# 16384 ~9.4 s.
GRID_RENDER_CHUNK = 8192


class GridModel(nn.Module):
    """The fast model: a factorised-grid field marched in fixed steps through the scene's
    box, skipping cells the occupancy grid knows are empty, and computing colour only for
    samples that carry weight."""

    # Inference marches this many steps at a time, and drops rays whose transmittance has
    # fallen below OPAQUE_TRANSMITTANCE: what they would still add is under 1e-4 of a pixel.
    # Training evaluates no colour past that point either (see _colour_where_visible).
    INFERENCE_SEGMENT = 32
    OPAQUE_TRANSMITTANCE = 1e-4
    render_chunk = GRID_RENDER_CHUNK

    def __init__(self, config: TrainConfig, box: SceneBounds, prior: OccupancyPrior | None = None) -> None:
        super().__init__()
        self.config = config
        self.field = GridField(config.grid, box)
        self.box_size = torch.tensor(box.box_max) - torch.tensor(box.box_min)
        self.prior = prior
        self._fit_sampling_to_grid()

    def _fit_sampling_to_grid(self) -> None:
        """Step length, samples per ray and occupancy cells follow the grid's vertices; the
        prior, where the dataset has one, marks empty space from the start."""
        cells = tuple(n - 1 for n in self.field.vertices)
        spacing = min(float(side) / count for side, count in zip(self.box_size, cells))
        self.step = self.config.grid_step_ratio * spacing
        self.samples_per_ray = math.ceil(float(self.box_size.norm()) / self.step) + 1
        # Alpha below this over one step is treated as empty space.
        self.density_threshold = -math.log1p(-self.config.occupancy_alpha_threshold) / self.step
        device = self.field.box_min.device
        self.occupancy = OccupancyGrid(self.field.box_min, self.field.box_max, cells).to(device)
        self.allowed: Tensor | None = None
        if self.prior is not None:
            box_min, box_max = self.field.box_min.tolist(), self.field.box_max.tolist()
            self.allowed = self.prior.allowed_cells(box_min, box_max, cells).to(device)
            self.occupancy.occupied.copy_(self.allowed)

    @torch.no_grad()
    def update_occupancy(self) -> None:
        """Re-mark empty space from the field's own density, never outside the prior. The
        threshold never exceeds the mean density (Instant-NGP's rule), so a young, still-faint
        field is never pruned to nothing."""
        density = self.field.vertex_density()
        threshold = min(self.density_threshold, float(density.mean()))
        self.occupancy.update_from_vertex_density(density, threshold, self.allowed)

    def resize(self, vertices: Vertices) -> None:
        self.field.resize(vertices)
        self._fit_sampling_to_grid()

    def before_step(self, iteration: int) -> bool:
        """Upsample on schedule and refresh the occupancy grid. Returns True when the
        parameters were replaced (the optimizer must be rebuilt)."""
        config = self.config
        resized = False
        if self.field.resolution_after(iteration) != self.field.resolution:
            self.resize(self.field.vertices_at(self.field.resolution_after(iteration)))
            self.update_occupancy()
            resized = True
        if iteration >= config.occupancy_warmup and iteration % config.occupancy_every == 0:
            self.update_occupancy()
        return resized

    def match_state(self, state: dict) -> None:
        """Take the vertices a checkpoint was saved with, so its tensors load (also cubic
        grids from before each axis had its own count)."""
        (nx, ny), nz = state["field.density_grid.planes.0"].shape[-2:], state["field.density_grid.planes.1"].shape[-1]
        if (nx, ny, nz) != self.field.vertices:
            self.resize((nx, ny, nz))

    def _march_edges(self, t_near: Tensor, t_far: Tensor, offset: Tensor, first: int, count: int) -> Tensor:
        """Edges ``[R, count+1]`` of march steps ``first .. first+count`` of each ray: fixed
        steps from ``t_near`` (the first shortened by ``offset`` of a step), cut at ``t_far``."""
        steps = torch.arange(first, first + count + 1, device=t_near.device, dtype=t_near.dtype)
        t_edges = t_near[:, None] + (steps[None, :] - 1.0 + offset).clamp_min(0.0) * self.step
        return torch.minimum(t_edges, t_far[:, None])

    # The helpers gather samples by flat index (one nonzero() per mask), which on the CPU
    # costs far less than boolean-mask indexing repeated per tensor.
    def _occupied_samples(self, positions: Tensor, deltas: Tensor) -> Tensor:
        """Flat indices of the samples ``positions [R, S, 3]`` that have a length and lie in
        occupied cells."""
        index = (deltas > 0).view(-1).nonzero().squeeze(1)
        return index[self.occupancy.query(positions.view(-1, 3).index_select(0, index))]

    def _density_at(self, positions: Tensor, index: Tensor, volume: Tensor | None, shape: torch.Size) -> Tensor:
        """Density ``shape = [R, S]`` at the samples ``index`` (0 elsewhere). ``volume``: the
        field's ``density_volume()`` (one trilinear read, no gradients) or None (the grids)."""
        inside = positions.view(-1, 3).index_select(0, index)
        values = self.field.density(inside) if volume is None else self.field.density_from_volume(volume, inside)
        return values.new_zeros(shape.numel()).index_put((index,), values).view(shape)

    @torch.no_grad()
    def _lit_samples(self, positions: Tensor, deltas: Tensor, index: Tensor) -> Tensor:
        """Of the samples ``index``, those that light still reaches (transmittance above
        ``OPAQUE_TRANSMITTANCE``), found in a pass without gradients: what lies behind an
        opaque surface adds under 1e-4 to the pixel, so training spends no backward pass on
        it (nerfacc's early stop), however solid the object. The pass reads the dense density
        volume (one trilinear read a sample; rebuilt once a step, about 1.5 ms at 68³)."""
        density = self._density_at(positions, index, self._density_volume(), deltas.shape)
        _, transmittance = render_weights(density, deltas)
        return index[transmittance.view(-1).index_select(0, index) > self.OPAQUE_TRANSMITTANCE]

    def _colour_where_visible(self, positions: Tensor, directions: Tensor, density: Tensor,
                              transmittance: Tensor) -> Tensor:
        """Colour ``[R, S, 3]``, evaluated only for samples with density that light still
        reaches (transmittance above ``OPAQUE_TRANSMITTANCE``): everything skipped behind
        that point adds less than ``OPAQUE_TRANSMITTANCE`` to the pixel, whatever its colour.

        Why not skip samples of low *weight* instead: a young field's samples all weigh
        little, so none would get a colour, each would count as black, and every bright
        pixel would push density down: a large white object then trains to empty space."""
        samples = density.shape[1]
        visible = (density.detach() > 0) & (transmittance.detach() > self.OPAQUE_TRANSMITTANCE)
        index = visible.view(-1).nonzero().squeeze(1)
        colour = self.field.colour(positions.view(-1, 3).index_select(0, index),
                                   directions.index_select(0, index // samples))
        return positions.new_zeros((positions.shape[0] * samples, 3)).index_put((index,), colour).view(positions.shape)

    def forward(
        self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
        background: Tensor | float = 1.0, generator: torch.Generator | None = None,
    ) -> list[RenderOutput]:
        if not self.training and not torch.is_grad_enabled():
            return [self._render_stopping_early(origins, directions, t_near, t_far, background)]
        rays = origins.shape[0]
        if self.training:  # one random offset per ray: unbiased, and every step still covered
            offset = torch.rand((rays, 1), generator=generator, device=origins.device, dtype=origins.dtype)
        else:
            offset = torch.zeros((rays, 1), device=origins.device, dtype=origins.dtype)
        t_edges = self._march_edges(t_near, t_far, offset, 0, self.samples_per_ray)
        deltas = t_edges[:, 1:] - t_edges[:, :-1]
        t_mid = interval_midpoints(t_edges)
        positions = origins[:, None, :] + directions[:, None, :] * t_mid[..., None]
        lit = self._lit_samples(positions, deltas, self._occupied_samples(positions, deltas))
        density = self._density_at(positions, lit, None, deltas.shape)
        weights, transmittance = render_weights(density, deltas)
        rgb = self._colour_where_visible(positions, directions, density, transmittance)
        return [RenderOutput(
            rgb=composite_rgb(weights, rgb, background), depth=expected_depth(weights, t_mid),
            opacity=weights.sum(dim=-1), weights=weights, t_edges=t_edges,
        )]

    def _density_volume(self) -> Tensor:
        """The field's density volume, rebuilt only when the field has changed."""
        parameters = list(self.field.parameters())
        key = tuple((id(p), p._version) for p in parameters)
        if getattr(self, "_volume_key", None) != key:
            self._volume = self.field.density_volume()
            self._volume_key = key
        return self._volume

    @torch.no_grad()
    def _render_stopping_early(
        self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor, background: Tensor | float,
    ) -> RenderOutput:
        """The same march without gradients, in segments of steps; a ray stops once it is
        opaque (transmittance below ``OPAQUE_TRANSMITTANCE``), so surfaces hide what lies
        behind them from the cost as well as from the image. Density comes from the dense
        density volume (equal to the grids' value, one lookup instead of six)."""
        volume = self._density_volume()
        rays = origins.shape[0]
        transmittance = origins.new_ones(rays)
        rgb = origins.new_zeros((rays, 3))
        depth = origins.new_zeros(rays)
        active = torch.arange(rays, device=origins.device)
        for first in range(0, self.samples_per_ray, self.INFERENCE_SEGMENT):
            count = min(self.INFERENCE_SEGMENT, self.samples_per_ray - first)
            ray_origins, ray_directions, ray_far = origins[active], directions[active], t_far[active]
            t_edges = self._march_edges(t_near[active], ray_far, origins.new_zeros((len(active), 1)), first, count)
            deltas = t_edges[:, 1:] - t_edges[:, :-1]
            t_mid = interval_midpoints(t_edges)
            positions = ray_origins[:, None, :] + ray_directions[:, None, :] * t_mid[..., None]
            density = self._density_at(positions, self._occupied_samples(positions, deltas), volume, deltas.shape)
            segment_weights, segment_transmittance = render_weights(density, deltas)
            entering = transmittance[active]
            weights = segment_weights * entering[:, None]
            colour = self._colour_where_visible(positions, ray_directions, density,
                                                segment_transmittance * entering[:, None])
            rgb.index_add_(0, active, accumulate(weights, colour))
            depth.index_add_(0, active, expected_depth(weights, t_mid))
            leaving = entering * segment_transmittance[:, -1] * torch.exp(-density[:, -1] * deltas[:, -1])
            transmittance[active] = leaving
            active = active[(leaving > self.OPAQUE_TRANSMITTANCE) & (t_edges[:, -1] < ray_far)]
            if active.numel() == 0:
                break
        opacity = 1.0 - transmittance
        return RenderOutput(rgb=rgb + transmittance[:, None] * background, depth=depth, opacity=opacity,
                            weights=None, t_edges=None)


def build_model(config: TrainConfig, box: SceneBounds | None, prior: OccupancyPrior | None = None) -> nn.Module:
    """The model ``config`` names; ``prior`` (grid models): where the scene can be."""
    if config.model == "nerf":
        return NerfModel(config)
    if config.model == "grid":
        if box is None:
            raise ValueError("the grid model needs the scene's box")
        return GridModel(config, box, prior)
    raise ValueError(f"unknown model {config.model!r}")


def final_output(outputs: list[RenderOutput]) -> RenderOutput:
    """The output whose image is the model's answer (the paper's fine pass)."""
    return outputs[-1]
