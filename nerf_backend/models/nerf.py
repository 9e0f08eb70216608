"""The paper's model: a coarse and a fine MLP field, rendered coarse-to-fine (Sec. 5.2)."""

from __future__ import annotations

import torch
from torch import Tensor

from ..core.scene_bounds import SceneBounds
from ..data.occupancy_prior import OccupancyPrior
from ..fields.mlp_field import FieldConfig, NerfField
from ..model_components.render_output import RenderOutput
from ..model_components.samplers import SamplingConfig, interval_midpoints, merge_edges, sample_pdf, stratified_edges
from ..model_components.volume_rendering import composite_rgb, expected_depth, render_weights
from .base import Model, ModelSettings


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
    deterministic. Rays with ``t_far <= t_near`` (they miss the scene's box) are not sent
    through the fields at all: they render as the background.
    """
    active = t_far > t_near
    if bool(active.all()):
        return _render_coarse_fine(coarse, fine, origins, directions, t_near, t_far, sampling, background,
                                   training, generator)
    index = active.nonzero().squeeze(-1)
    outputs = _render_coarse_fine(coarse, fine, origins[index], directions[index], t_near[index], t_far[index],
                                  sampling, background, training, generator)
    return tuple(None if out is None else _scatter(out, index, active.shape[0], background) for out in outputs)


def _scatter(out: RenderOutput, index: Tensor, rays: int, background: Tensor | float) -> RenderOutput:
    """Outputs for all ``rays`` from those of the active subset; the rest are background."""
    rgb = torch.empty((rays, 3), dtype=out.rgb.dtype, device=out.rgb.device)
    rgb[:] = torch.as_tensor(background, dtype=out.rgb.dtype, device=out.rgb.device)
    rgb = rgb.index_put((index,), out.rgb)
    zeros = out.depth.new_zeros(rays)
    weights = out.weights.new_zeros((rays, out.weights.shape[1])).index_put((index,), out.weights)
    edges = out.t_edges.new_zeros((rays, out.t_edges.shape[1])).index_put((index,), out.t_edges)
    return RenderOutput(rgb=rgb, depth=zeros.index_put((index,), out.depth),
                        opacity=zeros.index_put((index,), out.opacity), weights=weights, t_edges=edges)


def _render_coarse_fine(
    coarse: NerfField, fine: NerfField | None, origins: Tensor, directions: Tensor, t_near: Tensor,
    t_far: Tensor, sampling: SamplingConfig, background: Tensor | float, training: bool,
    generator: torch.Generator | None,
) -> tuple[RenderOutput, RenderOutput | None]:
    coarse_edges = stratified_edges(t_near, t_far, sampling.coarse_samples, jitter=training, generator=generator)
    coarse_out = render_pass(coarse, origins, directions, coarse_edges, background)
    if fine is None or sampling.fine_samples == 0:
        return coarse_out, None
    t_new = sample_pdf(
        coarse_edges, coarse_out.weights, sampling.fine_samples, deterministic=not training, generator=generator
    )
    fine_out = render_pass(fine, origins, directions, merge_edges(coarse_edges, t_new), background)
    return coarse_out, fine_out


class NerfModel(Model):
    """The paper's model: coarse field + (optional) fine field, rendered coarse-to-fine."""

    SETTINGS = {"field": FieldConfig, "sampling": SamplingConfig}

    def __init__(self, settings: ModelSettings) -> None:
        super().__init__()
        self.sampling = settings.sampling
        self.coarse = NerfField(settings.field)
        self.fine = NerfField(settings.field) if settings.sampling.fine_samples > 0 else None

    @classmethod
    def build(cls, settings: ModelSettings, box: SceneBounds | None, prior: OccupancyPrior | None) -> "NerfModel":
        return cls(settings)

    @property
    def image_field(self) -> NerfField:
        """The field the image comes from: the fine one, where there is one."""
        return self.fine if self.fine is not None else self.coarse

    def density_at(self, points: Tensor) -> Tensor:
        return self.image_field.density_features(points)[0]

    def colour_at(self, points: Tensor, directions: Tensor) -> Tensor:
        return self.image_field(points, directions)[1]

    def forward(
        self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
        background: Tensor | float = 1.0, generator: torch.Generator | None = None,
    ) -> list[RenderOutput]:
        coarse, fine = render_rays(
            self.coarse, self.fine, origins, directions, t_near, t_far,
            self.sampling, background, training=self.training, generator=generator,
        )
        return [coarse] if fine is None else [coarse, fine]
