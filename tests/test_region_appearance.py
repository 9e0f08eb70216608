"""Colour shaped by the scene's materials (issue 60; ``grid.region_appearance``): the colour
network's direction inputs by region (none on diffuse surfaces, the view reflected about the
true surface's normal on metal ones, the view elsewhere), the surface facts read from
a prior and its mesh, kept through a checkpoint, and deferred colour shading the same inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerf_backend.configs.presets import PRESETS
from nerf_backend.configs.train_config import with_overrides
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.data.occupancy_prior import OccupancyPrior
from nerf_backend.fields.grid_field import GridField, GridFieldConfig
from nerf_backend.models.registry import GridModel
from nerf_contract.dataset_layout import APPEARANCE_REGIONS

BOX = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
DIFFUSE, GLOSSY, METAL, THIN_FILM, TRANSMISSIVE = (APPEARANCE_REGIONS.index(name) for name in
                                                  ("diffuse", "glossy", "metal", "thin_film", "transmissive"))


def _field(deferred: bool = False) -> GridField:
    torch.manual_seed(0)
    config = GridFieldConfig(resolution=16, initial_resolution=16, region_appearance=True, deferred_colour=deferred)
    field = GridField(config, BOX)
    with torch.no_grad():  # a colour that depends on its inputs everywhere
        for parameter in field.parameters():
            parameter.normal_(0.0, 0.5)
    return field


def _facts(field: GridField, region_of_x: dict[str, int]) -> None:
    """Regions by the sign of x (``{"negative": r, "positive": r}``); every normal +z."""
    regions = torch.zeros((8, 8, 8), dtype=torch.uint8)
    regions[:4], regions[4:] = region_of_x["negative"], region_of_x["positive"]
    normals = torch.zeros((8, 8, 8, 3))
    normals[..., 2] = 1.0
    field.surface_facts.set(regions, normals, torch.full((3,), -1.0), torch.full((3,), 1.0))


def _directions(count: int, seed: int) -> torch.Tensor:
    d = torch.randn((count, 3), generator=torch.Generator().manual_seed(seed))
    return d / d.norm(dim=1, keepdim=True)


def test_diffuse_samples_are_the_same_colour_from_every_side_and_the_others_are_not():
    field = _field()
    _facts(field, {"negative": DIFFUSE, "positive": TRANSMISSIVE})
    point = torch.tensor([[-0.5, 0.1, 0.2], [0.5, 0.1, 0.2]])
    with torch.no_grad():
        colours = torch.stack([field.colour(point, d.expand(2, 3)) for d in _directions(6, 1)])
    assert float((colours[:, 0] - colours[0, 0]).abs().max()) == 0.0  # diffuse: no view at all
    assert float((colours[:, 1] - colours[0, 1]).abs().max()) > 1e-3  # transmissive: the view as before


def test_metal_samples_see_the_view_reflected_about_the_true_normal():
    """Direction inputs on metal: nothing of the view itself, the reflection encoding of
    d − 2 (d·n) n with n the surface's +z; on glossy (a dielectric) the view alone, as before."""
    field = _field()
    _facts(field, {"negative": METAL, "positive": GLOSSY})
    d = _directions(5, 2)
    view_width = field.direction_encoding.out_dims
    metal = field.direction_inputs(d, torch.tensor([[-0.5, 0.0, 0.0]]).expand(5, 3))
    reflected = d * torch.tensor([1.0, 1.0, -1.0])
    assert torch.equal(metal[:, :view_width], torch.zeros(5, view_width))
    torch.testing.assert_close(metal[:, view_width:], field.reflection_encoding(reflected), atol=1e-5, rtol=0)
    glossy = field.direction_inputs(d, torch.tensor([[0.5, 0.0, 0.0]]).expand(5, 3))
    torch.testing.assert_close(glossy[:, :view_width], field.direction_encoding(d))
    assert not glossy[:, view_width:].any()
    # No facts (a dataset without a prior): the view's encoding, the reflection's inputs zero.
    plain = _field()
    inputs = plain.direction_inputs(d, torch.zeros(5, 3))
    torch.testing.assert_close(inputs[:, :plain.direction_encoding.out_dims], plain.direction_encoding(d))
    assert not inputs[:, plain.direction_encoding.out_dims:].any()


def test_thin_film_samples_see_the_view_and_its_reflection():
    """A thin film's colour follows both what its coat mirrors and the angle to the normal (the
    interference): the view's encoding and the reflection encoding of d − 2 (d·n) n."""
    field = _field()
    _facts(field, {"negative": THIN_FILM, "positive": METAL})
    d = _directions(5, 4)
    view_width = field.direction_encoding.out_dims
    film = field.direction_inputs(d, torch.tensor([[-0.5, 0.0, 0.0]]).expand(5, 3))
    torch.testing.assert_close(film[:, :view_width], field.direction_encoding(d))
    reflected = d * torch.tensor([1.0, 1.0, -1.0])
    torch.testing.assert_close(film[:, view_width:], field.reflection_encoding(reflected), atol=1e-5, rtol=0)
    metal = field.direction_inputs(d, torch.tensor([[0.5, 0.0, 0.0]]).expand(5, 3))
    assert torch.equal(metal[:, :view_width], torch.zeros(5, view_width))  # metal still drops the view


def test_deferred_colour_shades_the_composited_direction_inputs():
    """A ray of one sample: deferred shading of its features and direction inputs is the
    sample's own colour, on diffuse, metal and unknown regions alike."""
    field = _field(deferred=True)
    _facts(field, {"negative": DIFFUSE, "positive": METAL})
    points = torch.tensor([[-0.5, 0.2, 0.1], [0.5, -0.3, 0.0], [1.5, 0.0, 0.0]])  # the last outside the facts
    d = _directions(3, 3)
    with torch.no_grad():
        carried = field.sample_appearance(field.appearance_grid(field.normalise(points)), d, points)
        shaded = field.shade_fn()(carried, d)
        own = field.colour(points, d)
    torch.testing.assert_close(shaded, own, atol=1e-6, rtol=0)


def _sphere_ply(path, radius: float) -> None:
    """A welded UV sphere as binary PLY, the way datasets_gen writes scene_geometry.ply."""
    rings, segments = 24, 48
    theta = np.linspace(0, math.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    vertices = (np.concatenate([[[0, 0, 1]], ring, [[0, 0, -1]]]) * radius).astype("<f4")
    at = lambda r, s: 1 + r * segments + s % segments  # noqa: E731
    faces = []
    for s in range(segments):
        faces.append([0, at(0, s), at(0, s + 1)])
        for r in range(rings - 2):
            faces += [[at(r, s), at(r + 1, s), at(r + 1, s + 1)], [at(r, s), at(r + 1, s + 1), at(r, s + 1)]]
        faces.append([len(vertices) - 1, at(rings - 2, s + 1), at(rings - 2, s)])
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\nproperty float x\n"
              f"property float y\nproperty float z\nelement face {len(faces)}\n"
              "property list uchar int vertex_indices\nend_header\n").encode()
    body = b"".join(bytes([3]) + np.asarray(f, "<i4").tobytes() for f in faces)
    path.write_bytes(header + vertices.tobytes() + body)


def test_a_model_takes_its_facts_from_the_prior_and_its_mesh_and_keeps_them_in_its_checkpoint(tmp_path):
    """A metal ball in a prior: the model's facts say metal on its surface, its normals point
    along its radius (within the angle of a facts cell), and a model built without the prior
    (as inference builds it) renders the same after loading the checkpoint."""
    radius, cells = 0.5, 40
    centres = (torch.arange(cells) + 0.5) / cells * 2.0 - 1.0
    x, y, z = torch.meshgrid(centres, centres, centres, indexing="ij")
    shell = ((x ** 2 + y ** 2 + z ** 2).sqrt() - radius).abs() < 2.0 / cells
    _sphere_ply(tmp_path / "scene_geometry.ply", radius)
    prior = OccupancyPrior(shell, (-1.0, -1.0, -1.0), 2.0 / cells, "surface", regions=(shell * METAL).to(torch.uint8),
                           geometry=tmp_path / "scene_geometry.ply")
    settings = with_overrides(PRESETS["fast"], ["grid.region_appearance=true"])
    model = GridModel(settings, BOX, prior)
    on_surface = _directions(200, 4) * radius
    region, normal = model.field.surface_facts.region_at(on_surface), model.field.surface_facts.normal_at(on_surface)
    assert (region == METAL).all()
    cell = 2.0 / 128
    angle = torch.rad2deg(torch.arccos((normal * on_surface / radius).sum(dim=1).clamp(-1, 1)))
    assert float(angle.max()) < math.degrees(cell * math.sqrt(3) / radius), float(angle.max())
    assert (model.field.surface_facts.region_at(torch.zeros(1, 3)) == 0).all()  # the ball's empty inside

    torch.save(model.state_dict(), tmp_path / "state.pt")
    again = GridModel(settings, BOX, None)
    again.restore(torch.load(tmp_path / "state.pt"))
    d = _directions(200, 5)
    with torch.no_grad():
        torch.testing.assert_close(again.field.colour(on_surface, d), model.field.colour(on_surface, d))
    with pytest.raises(ValueError, match="needs the samples' points"):
        model.field.direction_inputs(d)
