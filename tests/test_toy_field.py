"""Adding a field touches only the field's own file, the model registry and presets.json
(docs/design.md, "Where to add things"): a toy field of two dense voxel grids, defined here,
is registered, given a preset, trained by the real trainer, validated and scored, and its
settings are changed with --set, with nothing else in the backend changed."""

from __future__ import annotations

import json
from dataclasses import dataclass

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerf_backend.cli import main
from nerf_backend.configs import presets
from nerf_backend.configs.train_config import with_overrides
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.fields.base import MarchableField, SampleCost
from nerf_backend.models import registry
from nerf_backend.models.marched import MarchedModel
from nerf_backend.training.trainer import TrainOptions, train


# --- The field's own file: its settings and the field. ---
@dataclass(frozen=True)
class ToyFieldConfig:
    resolution: int = 24  # voxels along every side of the scene's box


DENSITY_SCALE = 50.0  # raw grid values to density: Adam's steps of about the learning rate move it fast enough


class ToyField(MarchableField):
    """Density and colour each in a dense voxel grid, read trilinearly: no view dependence."""

    SETTINGS_GROUP = "toy"
    Config = ToyFieldConfig

    def __init__(self, config: ToyFieldConfig, box: SceneBounds) -> None:
        super().__init__(box)
        side = config.resolution
        self.density_grid = nn.Parameter(torch.zeros(1, 1, side, side, side))
        self.colour_grid = nn.Parameter(torch.zeros(1, 3, side, side, side))
        self.cells = (side - 1,) * 3

    def _read(self, grid: Tensor, x: Tensor) -> Tensor:
        points = self.normalise(x).flip(-1).view(1, -1, 1, 1, 3)  # grid_sample reads (z, y, x)
        return F.grid_sample(grid, points, align_corners=True).view(grid.shape[1], -1).t()

    def density(self, x: Tensor) -> Tensor:
        return F.softplus(self._read(self.density_grid, x)[:, 0] * DENSITY_SCALE - 2.0)

    def colour(self, x: Tensor, directions: Tensor) -> Tensor:
        return torch.sigmoid(self._read(self.colour_grid, x))

    def occupancy_cells(self) -> tuple[int, int, int]:
        return self.cells

    def cell_max_density(self) -> Tensor:
        vertices = F.softplus(self.density_grid.detach()[0, 0] * DENSITY_SCALE - 2.0).permute(2, 1, 0)  # (x, y, z)
        return F.max_pool3d(vertices[None, None], kernel_size=2, stride=1)[0, 0]

    def occupancy_estimate(self) -> tuple[Tensor, float]:
        cell_max = self.cell_max_density()
        return cell_max, float(cell_max.mean())

    def sample_cost(self) -> dict[str, SampleCost]:
        read = SampleCost(gathers=8, flops=16)
        return {"density": read, "colour": read, "field": read + read, "frozen density": read}

    def encoding_parameters(self) -> list[nn.Parameter]:
        return [self.density_grid, self.colour_grid]


# Measured: 800 steps on the 40×40 demo dataset scored 21.57 dB on its validation views and
# 20.95 dB on its test views, where the blank white image scores 16.3 dB (14.5 to 16.3 on the
# test views). The floors say it learnt the scene (about 4 dB over the blank image), with room.
VALIDATION_PSNR_FLOOR_DB = 20.0


@pytest.fixture
def toy_preset(monkeypatch, tmp_path):
    """The two other places: the model registry's entry and a preset in presets.json."""
    monkeypatch.setitem(registry.MODELS, "toy", MarchedModel.of(ToyField))
    entries = json.loads(presets.PRESETS_FILE.read_text())
    entries["toy"] = {"label": "Toy", "description": "two dense voxel grids", "why": "the test's",
                      "extends": "fast", "settings": {"model": "toy", "toy": {"resolution": 32}, "iterations": 800}}
    path = tmp_path / "presets.json"
    path.write_text(json.dumps(entries))
    monkeypatch.setitem(presets.PRESETS, "toy", presets.load_presets(path)["toy"])
    return presets.PRESETS["toy"]


def test_a_new_field_trains_through_the_registry_and_a_preset(toy_preset, tiny_demo_dataset, tmp_path):
    assert toy_preset.toy == ToyFieldConfig(resolution=32) and toy_preset.model == "toy"
    assert with_overrides(toy_preset, ["toy.resolution=16"]).toy.resolution == 16
    run = tmp_path / "run"
    summary = train(TrainOptions(dataset=tiny_demo_dataset, run=run, preset="toy", seed=0, progress=False))
    assert summary.iteration == 800 and summary.stop_reason == "iterations"
    assert summary.val_psnr >= VALIDATION_PSNR_FLOOR_DB, summary.val_psnr
    config = json.loads((run / "config.json").read_text())
    assert config["config"]["toy"] == {"resolution": 32} and config["config"]["model"] == "toy"
    # Rendered and scored by the same commands as every other field.
    assert main(["eval", str(run), "--no-progress", "--device", "cpu"]) == 0
    assert json.loads((run / "metrics.json").read_text())["psnr"] >= VALIDATION_PSNR_FLOOR_DB - 2.0
