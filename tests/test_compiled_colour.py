"""Inference's compiled colour pass (kernels/colour_network.h through
field_components/compiled_colour.py) against PyTorch's float32 colour, which is the reference:
the grid read through PyTorch's own gather (``_forward_rows``), then the appearance basis, the
direction's encoding and the three layers. The same colours within 2e-6 (float32 rounding of
sums of 72 and 64 terms), on uneven sample counts (the pass goes in tiles), points inside, on
the border of and outside the box, any thread count."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.field_components import compiled_colour, compiled_grid
from nerf_backend.fields.grid_field import GridField, GridFieldConfig

BOX = SceneBounds((-0.7, -1.2, -0.4), (0.9, 1.1, 1.3))  # uneven sides: the normalisation per axis


@pytest.fixture(scope="module", autouse=True)
def library():
    found = compiled_grid.compiled_grid_library()
    if found is None:
        pytest.skip("no C compiler here: the compiled colour is not built (PyTorch colours)")
    return found


def _field(**settings) -> GridField:
    torch.manual_seed(3)
    config = dataclasses.replace(GridFieldConfig(initial_resolution=13, resolution=13), **settings)
    field = GridField(config, BOX).eval()
    with torch.no_grad():
        for parameter in field.parameters():
            parameter.normal_(0.0, 0.3)  # random weights: colours that differ, not the start's grey
    return field


def _reference(field: GridField, x: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    features = field.appearance_grid._forward_rows(field.normalise(x))
    return field.colour_from_grid(features, directions)


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("count", [1, 5, 6, 7, 4099])
def test_colours_match_pytorch_float32(threads, count, monkeypatch):
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    field = _field()
    generator = torch.Generator().manual_seed(count)
    directions = torch.nn.functional.normalize(torch.randn(37, 3, generator=generator), dim=-1)
    ray = torch.randint(0, 37, (count,), generator=generator)
    low, high = torch.tensor(BOX.box_min), torch.tensor(BOX.box_max)
    # 5 % past each side of the box: the grid's border fades as in PyTorch's read
    x = low + (torch.rand(count, 3, generator=generator) * 1.1 - 0.05) * (high - low)
    with torch.no_grad():
        colour = compiled_colour.compiled_ray_colour(field, directions)
        assert colour is not None
        actual = colour(x, ray)
        expected = _reference(field, x, directions.index_select(0, ray))
    assert actual.shape == (count, 3) and actual.dtype == torch.float32
    assert float((actual - expected).abs().max()) <= 2e-6
    if count > 1000:
        assert float(expected.std()) > 0.05


def test_the_pass_is_what_the_grid_field_colours_with_on_the_cpu():
    field = _field()
    directions = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    assert isinstance(field.ray_colour(directions), compiled_colour.CompiledRayColour)
    assert isinstance(field.ray_colour(directions, torch.bfloat16), compiled_colour.CompiledRayColour)


@pytest.mark.parametrize("settings, why", [
    ({"hidden_width": 32}, "a network of another width"),
    ({"appearance_channels": 12}, "channels that are not whole vectors of 8"),
])
def test_other_networks_colour_through_pytorch(settings, why):
    field = _field(**settings)
    directions = torch.nn.functional.normalize(torch.randn(9, 3), dim=-1)
    assert compiled_colour.compiled_ray_colour(field, directions) is None, why
    ray = torch.arange(9).repeat(3)
    x = torch.zeros(27, 3)
    with torch.no_grad():  # PyTorch's colour still runs
        assert torch.allclose(field.ray_colour(directions)(x, ray), _reference(field, x, directions[ray]), atol=1e-6)


def test_a_field_in_another_precision_colours_through_pytorch():
    field = _field().to(torch.float64)
    directions = torch.nn.functional.normalize(torch.randn(3, 3, dtype=torch.float64), dim=-1)
    assert compiled_colour.compiled_ray_colour(field, directions) is None
