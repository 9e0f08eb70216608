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
from .grid_field import GridField
from .occupancy import OccupancyGrid
from .ray_rendering import RenderOutput, render_rays
from .samplers import interval_midpoints
from .volume_rendering import composite_rgb, expected_depth, render_weights


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


class GridModel(nn.Module):
    """The fast model: a factorised-grid field marched in fixed steps through the scene's
    box, skipping cells the occupancy grid knows are empty, and computing colour only for
    samples that carry weight."""

    def __init__(self, config: TrainConfig, box: SceneBounds) -> None:
        super().__init__()
        self.config = config
        self.field = GridField(config.grid, box)
        self.box_size = torch.tensor(box.box_max) - torch.tensor(box.box_min)
        self._fit_sampling_to_grid()

    def _fit_sampling_to_grid(self) -> None:
        """Step length, samples per ray and occupancy cells follow the grid's resolution."""
        resolution = self.field.resolution
        voxel = float(self.box_size.max()) / (resolution - 1)
        self.step = self.config.grid_step_ratio * voxel
        self.samples_per_ray = math.ceil(float(self.box_size.norm()) / self.step) + 1
        # Alpha below this over one step is treated as empty space.
        self.density_threshold = -math.log1p(-self.config.occupancy_alpha_threshold) / self.step
        device = self.field.box_min.device
        self.occupancy = OccupancyGrid(self.field.box_min, self.field.box_max, resolution - 1).to(device)

    @torch.no_grad()
    def update_occupancy(self) -> None:
        """Re-mark empty space from the field's own density. The threshold never exceeds the
        mean density (Instant-NGP's rule), so a young, still-faint field is never pruned
        to nothing."""
        density = self.field.vertex_density()
        threshold = min(self.density_threshold, float(density.mean()))
        self.occupancy.update_from_vertex_density(density, threshold)

    def resize(self, resolution: int) -> None:
        self.field.resize(resolution)
        self._fit_sampling_to_grid()

    def before_step(self, iteration: int) -> bool:
        """Upsample on schedule and refresh the occupancy grid. Returns True when the
        parameters were replaced (the optimizer must be rebuilt)."""
        config = self.config
        resized = False
        if self.field.resolution_after(iteration) != self.field.resolution:
            self.resize(self.field.resolution_after(iteration))
            self.update_occupancy()
            resized = True
        if iteration >= config.occupancy_warmup and iteration % config.occupancy_every == 0:
            self.update_occupancy()
        return resized

    def match_state(self, state: dict) -> None:
        """Take the resolution a checkpoint was saved at, so its tensors load."""
        resolution = state["field.density_grid.planes.0"].shape[-1]
        if resolution != self.field.resolution:
            self.resize(resolution)

    def forward(
        self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
        background: Tensor | float = 1.0, generator: torch.Generator | None = None,
    ) -> list[RenderOutput]:
        rays, samples = origins.shape[0], self.samples_per_ray
        steps = torch.arange(samples + 1, device=origins.device, dtype=origins.dtype)
        if self.training:  # one random offset per ray: unbiased, and every step still covered
            offset = torch.rand((rays, 1), generator=generator, device=origins.device, dtype=origins.dtype)
        else:
            offset = torch.zeros((rays, 1), device=origins.device, dtype=origins.dtype)
        t_edges = t_near[:, None] + (steps[None, :] - 1.0 + offset).clamp_min(0.0) * self.step
        t_edges = torch.minimum(t_edges, t_far[:, None])
        deltas = t_edges[:, 1:] - t_edges[:, :-1]
        t_mid = interval_midpoints(t_edges)
        positions = origins[:, None, :] + directions[:, None, :] * t_mid[..., None]
        valid = deltas > 0
        valid[valid.clone()] = self.occupancy.query(positions[valid])
        density = torch.zeros((rays, samples), device=origins.device, dtype=origins.dtype)
        density = density.index_put((valid,), self.field.density(positions[valid]))
        weights, _ = render_weights(density, deltas)
        # Colour only where it shows: samples with visible weight.
        visible = weights.detach() > self.config.colour_weight_threshold
        rgb = torch.zeros((rays, samples, 3), device=origins.device, dtype=origins.dtype)
        view_dirs = directions[:, None, :].expand(rays, samples, 3)
        rgb = rgb.index_put((visible,), self.field.colour(positions[visible], view_dirs[visible]))
        output = RenderOutput(
            rgb=composite_rgb(weights, rgb, background), depth=expected_depth(weights, t_mid),
            opacity=weights.sum(dim=-1), weights=weights, t_edges=t_edges,
        )
        return [output]


def build_model(config: TrainConfig, box: SceneBounds | None) -> nn.Module:
    if config.model == "nerf":
        return NerfModel(config)
    if config.model == "grid":
        if box is None:
            raise ValueError("the grid model needs the scene's box")
        return GridModel(config, box)
    raise ValueError(f"unknown model {config.model!r}")


def final_output(outputs: list[RenderOutput]) -> RenderOutput:
    """The output whose image is the model's answer (the paper's fine pass)."""
    return outputs[-1]
