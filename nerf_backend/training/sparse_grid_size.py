"""The plenoxels preset's grid, from the dataset's pixel size and box.

A vertex of the sparse grid is learnt only from the rays that pass near it (nothing is shared
across the grid, as the factorised grids' planes are), so a grid finer than the training
pixels holds vertices no ray pins down: on the 40×40 demo a 256³ grid stayed blank after 300
steps (16.3 dB) where 64³ reached 32.2 dB. The final resolution is auto's (one vertex per
pixel footprint at the scene's centre, within auto's bounds), reached from half of it in one
growth; where the box is a guess it is narrowed to what the field fills at that growth, its
cells shrinking with it but not below the pixel's footprint.

Example (100×100 views at radius 4 of a 2-unit box):
    >>> import torch
    >>> from nerf_backend.configs.presets import PRESETS
    >>> from nerf_backend.core.cameras import Intrinsics
    >>> from nerf_backend.core.scene_bounds import SceneBounds
    >>> from nerf_backend.data.dataset import DatasetSplit
    >>> poses = torch.eye(4)[None].clone(); poses[:, 2, 3] = 4.0
    >>> split = DatasetSplit("train", Intrinsics(100, 100, 138.9, 138.9, 50.0, 50.0), poses,
    ...                      torch.zeros((1, 100, 100, 4), dtype=torch.uint8), [])
    >>> config, decisions = sparse_grid_size(PRESETS["plenoxels"], split, SceneBounds((-1,) * 3, (1,) * 3), None)
    >>> config.plenoxels.resolution, config.plenoxels.initial_resolution
    (71, 35)
"""

from __future__ import annotations

import dataclasses

from ..configs.train_config import TrainConfig
from ..core.scene_bounds import SceneBounds
from ..data.dataset import DatasetSplit
from .auto import MIN_RESOLUTION, pixel_footprint, pixel_resolution
from .decision import decide


def sparse_grid_size(config: TrainConfig, split: DatasetSplit, box: SceneBounds, profile: dict | None,
                     user_set: frozenset[str] = frozenset()) -> tuple[TrainConfig, dict]:
    """``config`` (a plenoxels preset) with its grid's final and initial resolution and finest
    cell from the pixel's footprint, and the box fitted at the growth where the box is a guess; the
    decisions with their reasons (what the user ``--set`` is kept)."""
    grid = config.plenoxels
    sides = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))
    footprint = pixel_footprint(split, box)
    chosen, reason = pixel_resolution(footprint, sides)  # type: ignore[arg-type]
    decisions: dict[str, dict] = {}
    resolution, decisions["grid_resolution"] = decide("plenoxels.resolution", chosen, reason, config, user_set)
    initial, decisions["initial_resolution"] = decide(
        "plenoxels.initial_resolution", max(MIN_RESOLUTION, resolution // 2),
        "half the final resolution (not below 32): one growth, when the coarse grid has found where the scene is",
        config, user_set)
    grown = resolution > initial and bool(grid.upsample_iterations)
    guessed = profile is None or profile.get("bounds") is None
    fit_box_at, decisions["box_fit"] = decide(
        "fit_box_at", grid.upsample_iterations[0] if grown and guessed else 0,
        ("the box is a guess (no scene bounds in the dataset): at the growth it narrows to what the field fills"
         if guessed else "the box is the scene's own bounds (scene_profile.json): it stays"), config, user_set)
    grid = dataclasses.replace(grid, resolution=resolution, initial_resolution=initial, finest_cell=footprint)
    shaped = config.with_settings(plenoxels=grid, fit_box_at=fit_box_at)
    return shaped, decisions
