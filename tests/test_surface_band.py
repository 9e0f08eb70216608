"""The band Blender's occupancy prior leaves a surface (``field_components/surface_band.py``)
and the surface field kept within it: a sphere voxelised by ``datasets_gen``'s own code
against its exact distance, and the field's projection after a step. The real scenes' priors
are checked against Blender's own ray hits in ``test_occupancy_prior.py``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from datasets_gen.core.voxelise import Part, voxelise
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.data.occupancy_prior import OccupancyPrior
from nerf_backend.field_components.surface_band import SignedDistanceBounds, band_distances
from nerf_backend.fields.surface_field import SurfaceField, SurfaceFieldConfig

RADIUS = 0.6
BOX = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def sphere_triangles(radius: float, rings: int = 96) -> np.ndarray:
    """[T, 3, 3] a latitude-longitude sphere fine enough that its faces lie within 0.02 % of
    ``radius`` of the sphere (checked below)."""
    theta = np.linspace(0.0, np.pi, rings + 1)
    phi = np.linspace(0.0, 2 * np.pi, 2 * rings + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = radius * np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)
    a, b, c, d = v[:-1, :-1], v[1:, :-1], v[1:, 1:], v[:-1, 1:]
    return np.concatenate([np.stack([a, b, c], axis=-2).reshape(-1, 3, 3), np.stack([a, c, d], axis=-2).reshape(-1, 3, 3)])


@pytest.fixture(scope="module")
def sphere_prior():
    """A sphere of radius 0.6 voxelised as datasets_gen does (64 cells, margin 1 cell)."""
    occupancy = voxelise([Part(sphere_triangles(RADIUS))], resolution=64, base_margin_cells=1)
    grid = occupancy.grid
    return OccupancyPrior(torch.from_numpy(occupancy.solid), tuple(grid.box_min.tolist()), grid.cell_size, "solid", 1,
                          torch.from_numpy(occupancy.surface))


def random_directions(count: int, seed: int) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(count, 3, generator=torch.Generator().manual_seed(seed)), dim=-1)


def bounds_of(prior: OccupancyPrior) -> SignedDistanceBounds:
    return SignedDistanceBounds(prior.surface_cells.numpy(), prior.occupied.numpy(), prior.box_min, prior.cell_size,
                                prior.margin_cells)


def test_the_true_surface_never_leaves_the_band_and_off_it_the_bounds_hold(sphere_prior):
    bounds, cell = bounds_of(sphere_prior), sphere_prior.cell_size
    directions = random_directions(20000, 0)
    lower, upper = bounds(directions * RADIUS)
    assert float(lower.max()) <= 0.0 and float(upper.min()) >= 0.0
    # Off the surface, at exact distances d from 0 to 6 cells either side: the bounds hold,
    # with the half cell of slack the prior's centre-to-centre distances leave.
    d = torch.linspace(-6, 6, 20000)[torch.randperm(20000, generator=torch.Generator().manual_seed(1))] * cell
    lower, upper = bounds(directions * (RADIUS + d[:, None]))
    exterior, interior = torch.isfinite(lower), torch.isfinite(upper)
    assert not bool((exterior & interior).any())
    assert float((lower - d)[exterior].max()) < -0.3 * cell
    assert float((-upper + d)[interior].max()) < -0.3 * cell
    # And the band is narrow: every point farther than 3 cells (the marks reach 2 cells past
    # the sphere's own cells) has its side fixed.
    far = d.abs() > 3 * cell
    assert bool((exterior | interior)[far].all())
    assert bool(exterior[d > 3 * cell].all()) and bool(interior[d < -3 * cell].all())


def test_band_distances_follow_the_margin():
    surface = np.zeros((15, 3, 3), bool)
    surface[3:12] = True  # a slab of 9 cells
    solid = surface.copy()
    for margin, band in ((0, 9), (1, 7), (3, 3)):
        outside, inside = band_distances(surface, solid, margin)
        assert int((outside[:, 1, 1] == 0).sum()) == band
        assert outside[0, 1, 1] == 3 + margin and inside.max() == 0


def test_the_field_is_projected_onto_the_band_after_each_step(sphere_prior):
    config = SurfaceFieldConfig(resolution=97, initial_resolution=49, upsample_iterations=(1,))
    field = SurfaceField(config, BOX, sphere_prior)
    assert field.take_note().startswith("the surface is kept within the band Blender's geometry marks")
    assert field.band is None  # built at the first step: rendering a checkpoint never pays for it
    cell = sphere_prior.cell_size
    directions = random_directions(4000, 2)
    with torch.no_grad():
        field.sdf_grid.values.sub_(20.0)  # the whole surface pushed 20 fine cells outward
    field.after_step()
    on_truth = field.signed_distance(directions * RADIUS).detach()
    assert float(on_truth.max()) <= 1e-6  # the truth is never outside the field's surface now
    # The vertices are bounded, so the zero level lies within a grid cell of the band: the
    # marks reach 2 prior cells past the sphere's cells, the band a cell less.
    grid_cell = 2.0 / 48
    outside = field.signed_distance(directions * (RADIUS + 3 * cell + grid_cell)).detach()
    assert float(outside.min()) >= 0.0
    # The bounds follow the grid as it grows, and hold at the new vertices.
    field.before_step(1)
    assert field.vertices == (97, 97, 97)
    with torch.no_grad():
        field.sdf_grid.values.add_(40.0)  # now 20 cells inward
    field.after_step()
    grid_cell = 2.0 / 96
    inside = field.signed_distance(directions * (RADIUS - 3 * cell - grid_cell)).detach()
    assert float(inside.max()) <= 0.0
    outside = field.signed_distance(directions * (RADIUS + 3 * cell + grid_cell)).detach()
    assert float(outside.min()) >= 0.0
    # Nothing of the band is saved: checkpoints stay those of a field without it.
    assert set(field.state_dict()) == set(SurfaceField(config, BOX).state_dict())


def test_without_the_prior_surface_cells_or_when_turned_off_nothing_is_bounded(sphere_prior):
    solid_only = OccupancyPrior(sphere_prior.occupied, sphere_prior.box_min, sphere_prior.cell_size, "solid", 1)
    turned_off = SurfaceFieldConfig(resolution=33, initial_resolution=33, prior_band=False)
    for field in (SurfaceField(SurfaceFieldConfig(resolution=33, initial_resolution=33), BOX, solid_only),
                  SurfaceField(turned_off, BOX, sphere_prior)):
        before = field.sdf_grid.values.detach().clone()
        with torch.no_grad():
            field.sdf_grid.values.sub_(20.0)
        field.after_step()
        assert torch.equal(field.sdf_grid.values.detach(), before - 20.0)
        assert field.take_note() is None
