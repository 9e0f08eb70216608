"""The backend's side of the occupancy prior: mapping the prior's cells onto a model's
occupancy grid never leaves out a cell that overlaps marked space, and a broken prior file
is a clear error naming it."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.core.errors import DatasetError
from nerf_backend.models.registry import GridModel
from nerf_backend.data.occupancy_prior import OccupancyPrior, load_occupancy_prior
from nerf_contract.dataset_layout import APPEARANCE_REGIONS


def _brute_force_allowed(prior: OccupancyPrior, box_min, box_max, cells) -> torch.Tensor:
    """Closed-interval overlap of every model cell with every marked prior cell, one by one."""
    marked = prior.occupied.nonzero().double()
    low = torch.tensor(prior.box_min, dtype=torch.float64) + marked * prior.cell_size
    high = low + prior.cell_size
    size = (torch.tensor(box_max, dtype=torch.float64) - torch.tensor(box_min, dtype=torch.float64)) / torch.tensor(cells)
    allowed = torch.zeros(cells, dtype=torch.bool)
    for index in np.ndindex(*cells):
        cell_low = torch.tensor(box_min, dtype=torch.float64) + torch.tensor(index) * size
        cell_high = cell_low + size
        allowed[index] = bool(((low <= cell_high + 1e-9) & (high >= cell_low - 1e-9)).all(dim=1).any())
    return allowed


@pytest.mark.parametrize("seed", range(4))
def test_allowed_cells_equal_a_brute_force_overlap(seed):
    generator = torch.Generator().manual_seed(seed)
    occupied = torch.rand((9, 7, 5), generator=generator) < 0.05
    prior = OccupancyPrior(occupied, (-1.0, -0.7, -0.4), 0.2, "surface")
    # A model box that sticks out of the prior's box on some sides and is inside on others.
    box_min, box_max, cells = (-1.3, -0.5, -0.6), (0.9, 0.8, 0.7), (6, 5, 4)
    assert torch.equal(prior.allowed_cells(box_min, box_max, cells), _brute_force_allowed(prior, box_min, box_max, cells))


def _brute_force_regions(prior: OccupancyPrior, box_min, box_max, cells) -> torch.Tensor:
    """Each model cell's region: the largest index among the prior cells it overlaps, one by one."""
    marked = prior.regions.nonzero()
    low = torch.tensor(prior.box_min, dtype=torch.float64) + marked.double() * prior.cell_size
    high = low + prior.cell_size
    values = prior.regions[tuple(marked.t())]
    size = (torch.tensor(box_max, dtype=torch.float64) - torch.tensor(box_min, dtype=torch.float64)) / torch.tensor(cells)
    out = torch.zeros(cells, dtype=torch.uint8)
    for index in np.ndindex(*cells):
        cell_low = torch.tensor(box_min, dtype=torch.float64) + torch.tensor(index) * size
        touching = ((low <= cell_low + size + 1e-9) & (high >= cell_low - 1e-9)).all(dim=1)
        out[index] = int(values[touching].max()) if bool(touching.any()) else 0
    return out


@pytest.mark.parametrize("seed", range(3))
def test_region_cells_equal_a_brute_force_overlap(seed):
    """A model cell takes the most view-dependent region of the prior cells it touches (a cell
    holding diffuse and glossy surfaces is glossy), 0 where it touches none."""
    generator = torch.Generator().manual_seed(seed)
    occupied = torch.rand((9, 7, 5), generator=generator) < 0.3
    regions = torch.randint(1, len(APPEARANCE_REGIONS), (9, 7, 5), generator=generator, dtype=torch.uint8) * occupied
    prior = OccupancyPrior(occupied, (-1.0, -0.7, -0.4), 0.2, "surface", regions=regions.to(torch.uint8))
    box_min, box_max, cells = (-1.3, -0.5, -0.6), (0.9, 0.8, 0.7), (11, 6, 4)
    mapped = prior.region_cells(box_min, box_max, cells)
    assert torch.equal(mapped, _brute_force_regions(prior, box_min, box_max, cells))
    assert set(mapped.unique().tolist()) >= {0, 1, len(APPEARANCE_REGIONS) - 1}  # the draw reaches every case
    assert torch.equal(mapped > 0, prior.allowed_cells(box_min, box_max, cells))  # each marked cell has a region
    no_regions = OccupancyPrior(occupied, (-1.0, -0.7, -0.4), 0.2, "surface")
    assert not no_regions.region_cells(box_min, box_max, cells).any()


def test_a_model_never_marks_a_cell_the_prior_leaves_out():
    occupied = torch.zeros((8, 8, 8), dtype=torch.bool)
    occupied[2:4, 3:5, 1:7] = True
    prior = OccupancyPrior(occupied, (-1.0, -1.0, -1.0), 0.25, "surface")
    model = GridModel(PRESETS["fast"], SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), prior)
    allowed = model.allowed.clone()
    assert 0.0 < allowed.float().mean() < 0.2
    assert torch.equal(model.occupancy.occupied, allowed)  # empty space skipped from the first step
    with torch.no_grad():  # a field dense everywhere still occupies only what the prior allows
        model.field.density_grid.planes[0].fill_(3.0)
        model.field.density_grid.lines[0].fill_(3.0)
    model.update_occupancy()
    assert torch.equal(model.occupancy.occupied, allowed)
    model.resize(model.field.vertices_at(96))  # upsampling maps the prior onto the new cells
    assert model.occupancy.occupied.shape == (95, 95, 95)
    assert torch.equal(model.occupancy.occupied, prior.allowed_cells((-1.0,) * 3, (1.0,) * 3, (95, 95, 95)))


def _write_prior(dataset, record, **arrays):
    dataset.mkdir(exist_ok=True)
    (dataset / "scene_profile.json").write_text(json.dumps({"occupancy_prior": record}))
    if arrays:
        np.savez_compressed(dataset / "occupancy_prior.npz", **arrays)


def test_the_priors_regions_load_beside_its_cells(tmp_path):
    surface = np.zeros((3, 2, 2), bool)
    surface[1:] = True
    regions = np.where(surface, np.uint8(2), np.uint8(0))
    regions[2] = 5
    _write_prior(tmp_path, {"file": "occupancy_prior.npz"}, surface=surface, solid=surface, regions=regions,
                 box_min=np.zeros(3), cell_size=np.array(0.5))
    for kind in ("surface", "solid"):
        prior = load_occupancy_prior(tmp_path, kind)
        assert prior.regions.dtype == torch.uint8 and torch.equal(prior.regions, torch.from_numpy(regions))
    assert prior.region_cells((0.0, 0.0, 0.0), (1.5, 1.0, 1.0), (3, 1, 1)).view(-1).tolist() == [2, 5, 5]


def test_a_dataset_without_a_prior_has_none(tmp_path):
    assert load_occupancy_prior(tmp_path, "surface") is None
    _write_prior(tmp_path, None)
    assert load_occupancy_prior(tmp_path, "surface") is None


@pytest.mark.parametrize("case, record, arrays, message", [
    ("missing file", {"file": "occupancy_prior.npz"}, {}, "occupancy_prior.npz: occupancy prior not found"),
    ("path outside", {"file": "../x.npz"}, {}, "'file' must be a file name in the dataset folder"),
    ("not bool", {"file": "occupancy_prior.npz"},
     {"surface": np.zeros((2, 2, 2), np.float32), "box_min": np.zeros(3), "cell_size": np.array(0.1)},
     "'surface' must be a 3-D bool array"),
    ("no kind", {"file": "occupancy_prior.npz"}, {"solid": np.zeros((2, 2, 2), bool)},
     "occupancy_prior.npz: not a readable occupancy prior"),
    ("bad cell", {"file": "occupancy_prior.npz"},
     {"surface": np.zeros((2, 2, 2), bool), "box_min": np.zeros(3), "cell_size": np.array(-1.0)},
     "'cell_size' a positive number"),
    ("regions not uint8", {"file": "occupancy_prior.npz"},
     {"surface": np.zeros((2, 2, 2), bool), "regions": np.zeros((2, 2, 2), np.int64), "box_min": np.zeros(3),
      "cell_size": np.array(0.1)}, "'regions' must be a uint8 array of the shape of 'surface' (2, 2, 2), got int64"),
    ("regions out of range", {"file": "occupancy_prior.npz"},
     {"surface": np.zeros((2, 2, 2), bool), "regions": np.full((2, 2, 2), 9, np.uint8), "box_min": np.zeros(3),
      "cell_size": np.array(0.1)}, "'regions' holds 9, not an index of the 6 regions (none, diffuse"),
])
def test_a_broken_prior_is_a_clear_error(tmp_path, case, record, arrays, message):
    _write_prior(tmp_path / "d", record, **arrays)
    with pytest.raises(DatasetError, match=re.escape(message)):
        load_occupancy_prior(tmp_path / "d", "surface")
