"""Everything that decides how a run trains, in one frozen dataclass; a run's ``config.json``
records it with every value, so a run can be reproduced. The presets are in presets.json.

The models' own settings are not listed here: each model names its groups (``Model.SETTINGS``),
and the config holds one of every registered model's groups, read as attributes
(``config.grid.resolution``) and written as top-level groups of ``config.json`` and
presets.json (``"grid": {"resolution": 128}``, ``--set grid.resolution=96``)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from typing import Any

from ..core.errors import NerfError
from ..models.registry import settings_groups

# How a run under a time budget counts its schedule (TrainConfig.schedule).
SCHEDULES = ("budget", "iterations")


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides how a run trains."""

    preset: str
    # A name in models.registry.MODELS: "nerf" (the paper's MLP fields, coarse-to-fine),
    # "grid" (factorised grids marched with an occupancy grid), "hash" (Instant-NGP's hash grid, marched).
    model: str = "nerf"
    # Every registered model's groups of settings, (name, frozen dataclass) in the registry's
    # order: "field" and "sampling" (the "nerf" model's), "grid", "hash"... (see the docstring).
    groups: tuple[tuple[str, Any], ...] = dataclasses.field(default_factory=lambda: default_groups())
    grid_step_ratio: float = 0.5  # marched models: step as a fraction of an occupancy cell
    occupancy_warmup: int = 16  # steps before empty space is skipped at all
    occupancy_every: int = 16
    occupancy_alpha_threshold: float = 1e-4  # cells that cannot reach this alpha in one step are empty
    # Rendering (no gradients) also skips the cells that cannot reach this alpha in one step:
    # faint haze a trained field leaves over empty space, which training keeps so that it can
    # still be trained away.
    render_alpha_threshold: float = 1e-2
    # Marched grid models: at this scheduled step, narrow the field to the box around its occupied
    # cells (the scene's box as the data gives it is often mostly empty: nerf_synthetic's
    # [-1.5, 1.5]³), keeping its cell count, and again after each later growth; 0: never (auto: at
    # the first growth).
    fit_box_at: int = 0
    # Marched models: rays that meet the scene's clear glass (from the occupancy prior: the
    # dataset's true surface and the IOR its profile gives) are bent through it and split by
    # Fresnel's equations, the field marched along each part (model_components/glass.py).
    refraction: bool = False
    # Grid models: start the occupancy grid from the dataset's occupancy prior (Blender's
    # geometry, occupancy_prior.npz) and never mark a cell it leaves out: "surface" (cells
    # the surfaces pass through, with a margin), "solid" (those and what they enclose), "none",
    # or "available" (auto's kind, solid, where the dataset has a prior; else none).
    occupancy_prior: str = "none"
    # "protocol": near 2, far 6 for every ray (the reference loaders). "scene": each ray's
    # entry and exit of the scene's bounding box from scene_profile.json (falls back to
    # "protocol" for datasets without one).
    ray_bounds: str = "protocol"
    rays_per_batch: int = 1024
    # The share of each batch drawn where the error is (training/error_map.py), after the
    # precrop; the rest uniformly over every pixel. 0: all uniform.
    error_sampling: float = 0.0
    # Coarse-to-fine images (data/image_pyramid.py): while the model still holds only coarse
    # detail (a grid before its last upsampling), its rays come from the images downsampled
    # to that detail, by powers of two; the full size once it holds its final detail.
    coarse_images: bool = False
    # Train on only the first N training views (the paper's 25/50/100-view ablation).
    max_train_views: int | None = None
    # The schedule's length: learning-rate decay, grid growth and centre crops are set in
    # these steps. Without a time budget the run stops after this many.
    iterations: int = 200_000
    # Under a time budget (--max-seconds): "budget" lays the schedule over the budget (its
    # step is the share of the budget spent times `iterations`, so decay, growth and crops
    # end with the budget); "iterations" counts steps taken whatever the budget (a run then
    # stops where the clock cuts its schedule).
    schedule: str = "budget"
    learning_rate: float = 5e-4
    # Learning rate of the MLPs when the model also has grids (which use learning_rate).
    network_learning_rate: float = 5e-4
    adam_betas: tuple[float, float] = (0.9, 0.999)
    # lr(step) = learning_rate · (final_learning_rate / learning_rate)^(step / lr_decay_steps)
    final_learning_rate: float = 5e-5
    lr_decay_steps: int = 500_000
    adam_eps: float = 1e-7
    # The decay never takes the learning rate below this fraction of its start: runs longer
    # than their schedule keep learning instead of freezing at a vanishing rate.
    learning_rate_floor: float = 0.01
    # "float32", or "bfloat16" / "float16": autocast runs the fields' products in that type
    # (volume rendering and the loss stay float32; float16 also scales the loss).
    precision: str = "float32"
    # Train on the centre of each image first: with a white background the all-white
    # image is a local minimum a NeRF falls into when most early rays miss the object.
    precrop_iterations: int = 500
    precrop_fraction: float = 0.5
    # Composite each training ray's ground truth and render over a random colour instead of
    # white: the alpha then decides, and "all background" stops being a minimum.
    random_background: bool = False
    validate_every: int = 2500
    # The collapse guard (collapse_guard.py): from this many steps on, a validation within
    # collapse_margin_db of the blank white image's PSNR on the same views is a collapse.
    collapse_check_after: int = 250
    collapse_margin_db: float = 1.0
    checkpoint_every: int = 1000
    # Validating and writing a checkpoint pause the training (on top of --max-seconds, which
    # counts steps): each kind is spaced so that it takes at most this share of the training
    # time, besides its step cadence (training/pauses.py); 0: on the step cadence alone.
    pause_share: float = 0.02
    log_every: int = 10

    def __getattr__(self, name: str) -> Any:
        # Only reached when no field has the name: a model's group of settings.
        for group, settings in self.__dict__.get("groups", ()):
            if group == name:
                return settings
        raise AttributeError(f"{type(self).__name__} has no setting {name!r}")

    def with_settings(self, **changes: Any) -> "TrainConfig":
        """This config with some settings changed, groups of settings too (``grid=...``)."""
        groups = dict(self.groups)
        for name in [name for name in changes if name in groups]:
            groups[name] = changes.pop(name)
        return dataclasses.replace(self, groups=tuple(groups.items()), **changes)

    def setting(self, key: str) -> Any:
        """The value of a dotted setting (``grid.resolution``, ``model``)."""
        value = self
        for part in key.split("."):
            value = getattr(value, part)
        return value

    def with_setting(self, key: str, value: Any) -> "TrainConfig":
        """This config with the dotted setting ``key`` set to ``value``.

        Example:
            >>> config = TrainConfig(preset="x").with_setting("rays_per_batch", 512)
            >>> config.rays_per_batch, config.with_setting("grid.resolution", 96).setting("grid.resolution")
            (512, 96)
        """
        group, _, name = key.partition(".")
        if not name:
            return self.with_settings(**{group: value})
        return self.with_settings(**{group: dataclasses.replace(getattr(self, group), **{name: value})})

    def learning_rate_decay(self, step: int) -> float:
        """The factor every learning rate is multiplied by at ``step`` (1 at the start)."""
        if self.learning_rate <= 0:  # a frozen model (learning_rate 0) has nothing to decay
            return 1.0
        ratio = self.final_learning_rate / self.learning_rate
        return max(ratio ** (step / self.lr_decay_steps), self.learning_rate_floor)

    def learning_rate_at(self, step: int) -> float:
        return self.learning_rate * self.learning_rate_decay(step)

    def scheduled_step(self, steps: int, spent: float | None, stop_at_iterations: bool = True) -> int:
        """The place in the schedule after ``steps`` steps, ``spent`` the share of the time
        budget used (None: no budget). With both a budget and an iteration count, the one
        nearer its end leads, so the schedule ends with whichever stops the run.

        Example:
            >>> config = TrainConfig(preset="x", iterations=3000)
            >>> config.scheduled_step(100, None), config.scheduled_step(100, 0.5, stop_at_iterations=False)
            (100, 1500)
        """
        if spent is None or self.schedule == "iterations":
            return steps
        by_time = int(self.iterations * min(max(spent, 0.0), 1.0))
        return max(steps, by_time) if stop_at_iterations else by_time

    def to_dict(self) -> dict:
        """Every setting, the models' groups at the top level after ``model``."""
        data: dict[str, Any] = {}
        for key, value in dataclasses.asdict(self).items():
            if key != "groups":
                data[key] = value
            if key == "model":
                data.update((name, dataclasses.asdict(settings)) for name, settings in self.groups)
        return data

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        values = dict(data)
        # Runs before colour was skipped by transmittance (GridModel.OPAQUE_TRANSMITTANCE)
        # stored a weight threshold; it no longer decides anything.
        values.pop("colour_weight_threshold", None)
        # A group a run lacks (the "hash" group in runs from before the hash field): its defaults.
        groups = tuple((name, _settings_from_dict(config_class, values.pop(name, {})))
                       for name, config_class in settings_groups().items())
        values["adam_betas"] = tuple(values["adam_betas"])
        values.setdefault("schedule", "iterations")  # runs from before budget schedules
        values.setdefault("coarse_images", False)  # runs from before coarse-to-fine images
        return cls(**values, groups=groups)


def default_groups() -> tuple[tuple[str, Any], ...]:
    """Each registered model's groups with their classes' defaults."""
    return tuple((name, config_class()) for name, config_class in settings_groups().items())


def _settings_from_dict(config_class: type, values: dict) -> Any:
    """A group's dataclass from its JSON object (JSON's lists back to the tuples it holds)."""
    tuples = {field.name for field in dataclasses.fields(config_class) if isinstance(field.default, tuple)}
    return config_class(**{key: tuple(value) if key in tuples else value for key, value in values.items()})


def with_overrides(config: TrainConfig, assignments: list[str]) -> TrainConfig:
    """``config`` with ``KEY=VALUE`` assignments applied; KEY may be dotted into the nested
    configs (``grid.resolution=96``, ``field.view_dependent=false``). Values are parsed as
    JSON where they can be (numbers, booleans, lists), else taken as strings."""
    data = config.to_dict()
    for assignment in assignments:
        key, sep, text = assignment.partition("=")
        if not sep:
            raise NerfError(f"--set {assignment!r}: expected KEY=VALUE")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        *parents, leaf = key.split(".")
        target = data
        for part in parents:
            if not isinstance(target.get(part), dict):
                raise NerfError(f"--set {key}: {part!r} is not a group of settings")
            target = target[part]
        if leaf not in target:
            raise NerfError(f"--set {key}: no such setting; known here: {', '.join(sorted(target))}")
        if isinstance(target[leaf], (int, float)) and not isinstance(target[leaf], bool) and not isinstance(value, (int, float)):
            raise NerfError(f"--set {key}: expected a number, got {text!r}")
        target[leaf] = value
    try:
        return TrainConfig.from_dict(data)
    except TypeError as exc:
        raise NerfError(f"--set: {exc}") from None
