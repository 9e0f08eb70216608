"""The backend's side of the occupancy prior: mapping the prior's cells onto a model's
occupancy grid never leaves out a cell that overlaps marked space, and a broken prior file
is a clear error naming it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.core.errors import DatasetError
from nerf_backend.models.registry import GridModel
from nerf_backend.data.occupancy_prior import OccupancyPrior, load_occupancy_prior


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
])
def test_a_broken_prior_is_a_clear_error(tmp_path, case, record, arrays, message):
    _write_prior(tmp_path / "d", record, **arrays)
    with pytest.raises(DatasetError, match=message.replace("(", r"\(")):
        load_occupancy_prior(tmp_path / "d", "surface")
