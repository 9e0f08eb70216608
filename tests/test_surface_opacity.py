"""Where a surface field's silhouette lies: VolSDF's density outside the surface piles up along
rays that graze it, so its silhouette lies outside the distance's zero level (and training
pulls the surface inward to match the images); NeuS's opacity halves a ray's transmittance
exactly at the zero level, for rays that cross it head on and for rays that graze it. Measured
on the surface field's starting sphere, through the model's own inference march."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.errors import NerfError
from nerf_backend.core.scene_bounds import SceneBounds, vertices_for
from nerf_backend.models.registry import build_model

BOX = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
RADIUS = 0.5  # the field's starting sphere: initial_radius 0.5 of the box's half-side


def _sphere_model(opacity: str):
    config = PRESETS["surface"]
    config = config.with_settings(surface=dataclasses.replace(config.surface, opacity=opacity))
    model = build_model(config, BOX)
    model.resize(vertices_for(config.surface.resolution, model.field.extent))
    model.field.beta.fill_(model.field.final_beta)  # the sharpest the schedule makes it: half a cell
    model.update_occupancy()
    return model.eval()


def _opacity_across_the_edge(model, offsets: torch.Tensor) -> torch.Tensor:
    """Opacity of rays along +x passing at ``offsets`` from the sphere's centre (in y)."""
    origins = torch.stack([torch.full_like(offsets, -3.0), offsets, torch.zeros_like(offsets)], dim=-1)
    directions = torch.tensor([[1.0, 0.0, 0.0]]).expand_as(origins).contiguous()
    near, far = torch.full_like(offsets, 2.0), torch.full_like(offsets, 4.0)
    with torch.no_grad():
        return model(origins, directions, near, far)[-1].opacity


def _half_opacity_offset(model) -> float:
    cell = 2.0 / (max(model.field.vertices) - 1)
    offsets = torch.linspace(RADIUS - 4 * cell, RADIUS + 4 * cell, 801)
    opacity = _opacity_across_the_edge(model, offsets)
    assert opacity[0] > 0.99 and opacity[-1] < 0.01  # the sphere's inside, and beyond it
    first_below = int((opacity < 0.5).nonzero()[0])
    a, b = opacity[first_below - 1], opacity[first_below]  # interpolate between the two offsets
    edge = offsets[first_below - 1] + (a - 0.5) / (a - b) * (offsets[first_below] - offsets[first_below - 1])
    return float(edge - RADIUS) / cell


def test_neus_opacity_puts_the_silhouette_on_the_zero_level_and_volsdf_outside_it():
    volsdf, neus = _half_opacity_offset(_sphere_model("volsdf")), _half_opacity_offset(_sphere_model("neus"))
    # A grazing ray's optical depth outside a sphere of R cells with β = half a cell is about
    # 0.5·sqrt(2πR/β)·exp(−s/β): it reaches ln 2 at s ≈ 1.4 cells for R = 48 (measured 1.40).
    assert 1.0 < volsdf < 1.8, volsdf
    assert abs(neus) < 0.1, neus  # measured −0.05: the trilinear sphere is a little small


def test_neus_opacity_is_opaque_head_on_and_transparent_where_the_distance_grows():
    model = _sphere_model("neus")
    through_centre = _opacity_across_the_edge(model, torch.zeros(1))
    assert float(through_centre) > 0.999
    field = model.field
    x = torch.tensor([[0.0, 0.0, 0.0], [RADIUS, 0.0, 0.0], [-RADIUS, 0.0, 0.0]])
    outward = torch.tensor([[1.0, 0.0, 0.0]]).expand(3, 3)
    with torch.no_grad():
        density = field.density_along(x, outward)  # leaving the sphere at +x, entering it at −x along +x
    assert density[1] == 0.0 and density[0] == 0.0  # the distance grows (or is flat deep inside)
    entering = density[2]
    step = field.march_step
    # Entering head on at the zero level: −ln(Φ(−h/2)/Φ(h/2)) / h over the step h, Φ the logistic
    # of s/β, for the exact distance; the grid's trilinear sphere is read between vertices
    # (y = 0 falls midway), where it is a little smaller: measured 90.9 against 95.5.
    beta = float(field.beta)
    phi = torch.sigmoid(torch.tensor([-step / 2, step / 2]) / beta)
    expected = -torch.log(phi[0] / phi[1]) / step
    assert float(entering) == pytest.approx(float(expected), rel=0.1)


def test_an_unknown_opacity_is_a_clear_error():
    config = PRESETS["surface"]
    with pytest.raises(NerfError, match="surface.opacity 'nerf': choose volsdf or neus"):
        build_model(config.with_settings(surface=dataclasses.replace(config.surface, opacity="nerf")), BOX)
