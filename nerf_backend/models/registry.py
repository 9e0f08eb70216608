"""Every model by the name a preset gives it (``TrainConfig.model``): a new model is one
entry here."""

from __future__ import annotations

from ..core.errors import NerfError
from ..core.scene_bounds import SceneBounds
from ..data.occupancy_prior import OccupancyPrior
from .base import Model, ModelSettings
from .marched import GridModel, HashModel
from .nerf import NerfModel

MODELS: dict[str, type[Model]] = {
    "nerf": NerfModel,  # the paper's MLPs, coarse-to-fine
    "grid": GridModel,  # factorised grids + occupancy march (the fast preset)
    "hash": HashModel,  # multiresolution hash grid + occupancy march (Instant-NGP)
}


def model_class(name: str) -> type[Model]:
    try:
        return MODELS[name]
    except KeyError:
        raise NerfError(f"unknown model {name!r}; choose one of {', '.join(MODELS)}") from None


def build_model(settings: ModelSettings, box: SceneBounds | None, prior: OccupancyPrior | None = None) -> Model:
    """The model ``settings.model`` names, over the scene's ``box``; ``prior`` (marched
    models): where the scene can be."""
    return model_class(settings.model).build(settings, box, prior)
