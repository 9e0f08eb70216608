"""Training presets. A preset fixes the model, the sampling and the optimiser; a run's
``config.json`` records the preset used, with every value, so a run can be reproduced."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from .errors import NerfError
from .fields import FieldConfig
from .ray_rendering import SamplingConfig


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides how a run trains."""

    preset: str
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    sampling: SamplingConfig = dataclasses.field(default_factory=SamplingConfig)
    # "protocol": near 2, far 6 for every ray (the reference loaders). "scene": each ray's
    # entry and exit of the scene's bounding box from scene_profile.json (falls back to
    # "protocol" for datasets without one).
    ray_bounds: str = "protocol"
    rays_per_batch: int = 1024
    iterations: int = 200_000
    learning_rate: float = 5e-4
    # lr(step) = learning_rate · (final_learning_rate / learning_rate)^(step / lr_decay_steps)
    final_learning_rate: float = 5e-5
    lr_decay_steps: int = 500_000
    adam_eps: float = 1e-7
    # Train on the centre of each image first: with a white background the all-white
    # image is a local minimum a NeRF falls into when most early rays miss the object.
    precrop_iterations: int = 500
    precrop_fraction: float = 0.5
    validate_every: int = 2500
    checkpoint_every: int = 1000
    log_every: int = 10

    def learning_rate_at(self, step: int) -> float:
        ratio = self.final_learning_rate / self.learning_rate
        return self.learning_rate * ratio ** (step / self.lr_decay_steps)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        values = dict(data)
        values["field"] = FieldConfig(**{**values["field"], "skips": tuple(values["field"]["skips"])})
        values["sampling"] = SamplingConfig(**values["sampling"])
        return cls(**values)


PRESETS: dict[str, TrainConfig] = {
    # The paper's NeRF as its authors trained it on nerf_synthetic: 8×256 MLP with a skip,
    # L = 10 / 4, 64 coarse + 128 fine samples, 1024 rays, lr 5e-4 decaying ×0.1 per 500k steps.
    "paper": TrainConfig(preset="paper"),
    # The same code path scaled down to reach a useful image in a few CPU minutes: a 4×128
    # MLP, fewer samples, spent only inside the scene's box.
    "preview": TrainConfig(
        preset="preview",
        field=FieldConfig(
            depth=4, width=128, skips=(2,), position_frequencies=8, direction_frequencies=4,
            colour_width=64, density_activation="softplus",
        ),
        sampling=SamplingConfig(coarse_samples=32, fine_samples=32),
        ray_bounds="scene",
        rays_per_batch=512,
        iterations=3000,
        learning_rate=2e-3,
        final_learning_rate=2e-4,
        lr_decay_steps=3000,
        precrop_iterations=200,
        validate_every=250,
        checkpoint_every=250,
    ),
}


def preset_config(name: str) -> TrainConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise NerfError(f"unknown preset {name!r}; choose one of {', '.join(sorted(PRESETS))}") from None
