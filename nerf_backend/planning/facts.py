"""What a run's plan is decided from: the user's request (its preset with their ``--set``, or
a resumed run's stored settings, is where the plan starts) and what the dataset, the run folder
and this machine hold. Gathering them is the plan's only reading; the rules are pure functions
of them (``rules.py``).

Example:
    >>> sorted(RunRequest(overrides=("grid.resolution=96", "rays_per_batch=512")).user_set)
    ['grid.resolution', 'rays_per_batch']
    >>> starting_settings(RunRequest(preset="fast", overrides=("rays_per_batch=512",)), None).rays_per_batch
    512
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from nerf_contract.dataset_layout import transforms_name

from ..configs.presets import DEFAULT_PRESET, preset_config
from ..configs.train_config import TrainConfig, with_overrides
from ..core.devices import present_devices
from ..core.errors import RunError
from ..core.scene_bounds import SceneBounds
from ..data.dataset import DatasetSplit, load_scene_bounds, load_scene_profile, load_split
from ..data.occupancy_prior import PRIOR_KINDS, OccupancyPrior, load_occupancy_prior
from ..data.run_folder import RunFolder


@dataclass(frozen=True)
class RunRequest:
    """What the user asked of a run (``train``'s arguments that shape its plan)."""

    preset: str | None = None  # None: DEFAULT_PRESET for a new run, the run's own on resume
    overrides: tuple[str, ...] = ()  # KEY=VALUE changes to the preset (new runs only)
    iterations: int | None = None  # total for the run; None: the preset's
    max_seconds: float | None = None  # total training seconds for the run
    # The time budget the schedule is laid over (TrainConfig.schedule); None: max_seconds.
    # The bench stops a run at points along its budget to score it, on one schedule.
    schedule_seconds: float | None = None
    seed: int = 0
    device: str = "auto"
    resume: bool = False
    # The dotted settings the user gave with --set: theirs, whatever a rule would choose.
    user_set: frozenset[str] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "user_set", frozenset(assignment.partition("=")[0] for assignment in self.overrides))


@dataclass(frozen=True)
class RunFacts:
    """Everything a plan is decided from, read once."""

    request: RunRequest
    start: TrainConfig  # the settings the plan starts from: the preset with --set, or the stored ones
    dataset: Path
    train_split: DatasetSplit  # every training view (the plan may train on fewer)
    profile: dict | None  # scene_profile.json: what Blender knew of the scene
    scene_bounds: SceneBounds | None
    priors: Mapping[str, OccupancyPrior]  # the dataset's occupancy priors by kind (none: empty)
    devices: tuple[str, ...]  # the devices present, fastest first
    stored: dict | None = None  # a resumed run's config.json
    val_split: DatasetSplit | None = None  # the views validation renders as training goes (None: none)


def gather_facts(dataset: Path, run: RunFolder, request: RunRequest, with_val: bool = False) -> RunFacts:
    """Reads the run's stored config (when resuming), the dataset's training views (its
    validation views too, ``with_val``, where it has them), profile, bounds and priors, and the
    devices present. Bad input (a broken dataset, a bad ``--set``, a resume that would change
    the run) is a clear error here, before the run folder is touched."""
    dataset = Path(dataset).resolve()
    stored = run.read_config() if request.resume else None
    if stored is not None:
        _check_resume(request, stored, dataset, run.path)
    train_split = load_split(dataset, "train")
    val_split = load_split(dataset, "val") if with_val and (dataset / transforms_name("val")).exists() else None
    profile, bounds = load_scene_profile(dataset), load_scene_bounds(dataset)
    priors = {kind: prior for kind in PRIOR_KINDS if (prior := load_occupancy_prior(dataset, kind)) is not None}
    return RunFacts(request, starting_settings(request, stored), dataset, train_split, profile, bounds, priors,
                    present_devices(), stored, val_split)


def starting_settings(request: RunRequest, stored: dict | None) -> TrainConfig:
    """A new run's preset with the user's ``--set``; a resumed run's stored settings."""
    if stored is not None:
        return TrainConfig.from_dict(stored["config"])
    return with_overrides(preset_config(request.preset or DEFAULT_PRESET), list(request.overrides))


def _check_resume(request: RunRequest, stored: dict, dataset: Path, run: Path) -> None:
    """A resume continues the stored run as it was: refused where the request would change it."""
    if request.preset is not None and request.preset != stored["preset"]:
        raise RunError(f"{run}: run was trained with preset {stored['preset']!r}, not {request.preset!r}")
    if Path(stored["dataset"]) != dataset:
        raise RunError(f"{run}: run was trained on {stored['dataset']}, not {dataset}")
    if request.overrides:
        raise RunError(f"{run}: --set applies to new runs; a resumed run keeps its config")
