"""Every model by the name a preset gives it (``TrainConfig.model``): a new model is one
entry here. A marched field needs no model code of its own: ``MarchedModel.of(TheField)``."""

from __future__ import annotations

from ..core.errors import NerfError
from ..core.scene_bounds import SceneBounds
from ..data.occupancy_prior import OccupancyPrior
from ..fields.grid_field import GridField
from ..fields.hash_field import HashField
from ..fields.plenoxel_field import PlenoxelField
from ..fields.surface_field import SurfaceField
from .base import Model, ModelSettings
from .marched import MarchedModel
from .nerf import NerfModel

GridModel = MarchedModel.of(GridField)  # factorised grids + occupancy march (the fast preset)
HashModel = MarchedModel.of(HashField)  # multiresolution hash grid + occupancy march (Instant-NGP)
SurfaceModel = MarchedModel.of(SurfaceField)  # a signed distance in a dense grid, rendered as VolSDF's density
PlenoxelModel = MarchedModel.of(PlenoxelField)  # a sparse voxel grid of density and harmonics (Plenoxels)

MODELS: dict[str, type[Model]] = {
    "nerf": NerfModel,  # the paper's MLPs, coarse-to-fine
    "grid": GridModel,
    "hash": HashModel,
    "surface": SurfaceModel,
    "plenoxels": PlenoxelModel,
}


def model_class(name: str) -> type[Model]:
    try:
        return MODELS[name]
    except KeyError:
        raise NerfError(f"unknown model {name!r}; choose one of {', '.join(MODELS)}") from None


def settings_groups() -> dict[str, type]:
    """Every registered model's groups of settings by name, in the registry's order (a run's
    config holds one of each); two models naming one group must mean the same class."""
    groups: dict[str, type] = {}
    for name, model in MODELS.items():
        for group, config_class in model.SETTINGS.items():
            if groups.setdefault(group, config_class) is not config_class:
                raise NerfError(f"model {name!r}: settings group {group!r} is another model's {groups[group].__name__}")
    return groups


def build_model(settings: ModelSettings, box: SceneBounds | None, prior: OccupancyPrior | None = None) -> Model:
    """The model ``settings.model`` names, over the scene's ``box``; ``prior`` (marched
    models): where the scene can be."""
    return model_class(settings.model).build(settings, box, prior)
