"""The ``auto`` preset: the fast model, shaped by what the scene needs.

Blender knows the scene, and the dataset carries that knowledge (``scene_profile.json``)
along with the images. Each decision is returned with its reason and recorded in the
run's ``config.json``:

- model: the factorised grids, measured against the other models at equal time (the plenoxels
  preset's sparse voxel grid lost by 5.3 dB on lego at 10 minutes on 2 CPU cores);
- rays a step: 2 048, measured against 1 024 and 4 096 on lego at 2 and 10 minutes, and against
  1 024 on the shared real scenes at 100×100;
- bounds: the scene's box (from the profile) limits every ray and the grids; without it the
  box is a guess, narrowed at the first growth to what the field has filled (``fit_box_at``) and
  again after each later growth, as the finer grid bounds the scene closer;
- view dependence: no glossy, metallic, specular, transmissive, clearcoat or sheen material
  → colour takes no direction input;
- detail: the grid needs no vertex finer than the footprint of a pixel on the scene
  (Nyquist for the training images), so its resolution is the box size over that footprint,
  up to a limit that a budget of 30 minutes or more raises (measured on lego);
- samples: one march step per grid cell covers the depth range at that same detail;
- time: under a time budget the grid's last growth waits for steps enough to fill it in; a
  budget too short for the final grid keeps it one growth coarser;
- background: a transparent film gives an alpha channel, so training composites over
  random colours and the alpha decides what is background;
- empty space: where the dataset carries Blender's own geometry as an occupancy prior,
  the occupancy grid starts from it and never marks what it leaves out, so empty space is
  skipped from the first step and nothing can grow there.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from ..configs.train_config import TrainConfig
from ..core.scene_bounds import SceneBounds, vertices_for
from ..data.dataset import DatasetSplit
from ..models.marched import FIT_MAX_KEPT, REFIT_MAX_KEPT
from .decision import decide

MIN_RESOLUTION, MAX_RESOLUTION = 32, 256
# A budget this long grows the grid up to LONG_BUDGET_RESOLUTION instead (docs/benchmarks_lego.md,
# "A finer grid for a longer budget"): more vertices need more steps to fill in, and make every
# view slower to render.
LONG_BUDGET_SECONDS = 1800.0
LONG_BUDGET_RESOLUTION = 384
FINEST_REASON = (
    "measured on lego at 800×800 on 2 CPU cores: 384 vertices along the longest side scored 35.00 dB after 30 "
    "minutes against 256's 34.54, and 33.04 after 10 as 256 did, while its views rendered 1.4 times slower "
    "(17.0-17.4 s for 13 views against 11.7-12.3)")
# Which of the prior's fills auto uses (measured with bench: see the README).
PRIOR_KIND = "solid"
# Steps a time budget must still allow (at the run's rate so far) for the grid's last growth:
# RobotExpressive at 800×800 without a prior had about 1 000 left at 60 s (the coarser grid then
# better) and 2 200 at 120 s (the final grid as good); held back with 60 s, three real scenes
# scored 0.19-1.17 dB more (docs/benchmarks_800px.md, "auto sizes its grid for the budget").
LAST_GROWTH_MIN_STEPS = 1500
# The model auto trains, chosen by measurement against the others at equal time (the bench
# tables of docs/benchmarks_lego.md and docs/benchmarks_800px.md).
MODEL = "grid"
MODEL_REASON = (
    "the factorised grids (the fast preset's model), measured against the plenoxels preset (a sparse voxel grid "
    "of density and harmonics, no network) on lego at 800×800 on 2 CPU cores, they scored 28.04 dB after 2 minutes "
    "against 21.01, and 31.88 after 10 against 26.58 (docs/benchmarks_lego.md, \"Plenoxels\")")
# Rays a step, chosen by measurement on 2 CPU cores (docs/benchmarks_lego.md, "Rays a step"): a
# step's fixed costs are shared by more rays.
RAYS_PER_STEP = 2048
RAYS_REASON = (
    "measured on lego at 800×800 on 2 CPU cores, with the box fitted again at each growth: 2 048 rays a step scored "
    "28.20 dB after 2 minutes against 1 024's 27.99, and 33.04 after 10 against 32.58 (they move 1.2-1.5 times "
    "as many rays a second: a step's fixed costs are shared by more rays); 4 096 lost at 2 minutes (25.65 dB "
    "against 28.25 before the refit); on the three shared real scenes at 100×100, 2 048 scored 0.19-0.42 dB more "
    "after 2 minutes (docs/benchmarks_lego.md, \"Rays a step\" and \"The box fitted again\")")
# occupancy_prior's value for "PRIOR_KIND where the dataset has a prior, else none".
AVAILABLE_PRIOR = "available"


def pixel_footprint(split: DatasetSplit, box: SceneBounds) -> float:
    """Mean size (world units) of one pixel at the box's centre, over the training cameras."""
    centre = (torch.tensor(box.box_min) + torch.tensor(box.box_max)) / 2
    distances = (split.poses[:, :3, 3] - centre).norm(dim=-1)
    focal = (split.intrinsics.fl_x + split.intrinsics.fl_y) / 2
    return float(distances.mean()) / focal


def finest_resolution(budget_seconds: float | None) -> tuple[int, str]:
    """The most vertices along the box's longest side auto grows its grid to within a time
    budget (None: no budget), and why."""
    if budget_seconds is not None and budget_seconds >= LONG_BUDGET_SECONDS:
        return LONG_BUDGET_RESOLUTION, (f"a budget of {budget_seconds / 60:g} minutes (at least "
                                        f"{LONG_BUDGET_SECONDS / 60:g}) grows it up to {LONG_BUDGET_RESOLUTION}: "
                                        f"{FINEST_REASON}")
    budget = "no time budget" if budget_seconds is None else f"a budget of {budget_seconds / 60:g} minutes"
    return MAX_RESOLUTION, (f"{budget} (under {LONG_BUDGET_SECONDS / 60:g}) grows it up to {MAX_RESOLUTION}: "
                            f"{FINEST_REASON}")


def pixel_resolution(footprint: float, sides: tuple[float, float, float], cubic_cells: bool = True,
                     most: int = MAX_RESOLUTION) -> tuple[int, str]:
    """Vertices along the box's longest side that resolve a pixel of ``footprint`` (world
    units) in a box of ``sides`` (with cubic cells: a cube's cells spread over the box), within
    [MIN_RESOLUTION, most], and why."""
    extent = max(sides)
    per_pixel = math.ceil(extent / footprint) + 1
    reason = (f"a pixel covers {footprint:.4f} units at the scene's centre and the box is {extent:.3f} across: "
              f"{per_pixel} vertices a side resolve every pixel")
    wanted = per_pixel
    if cubic_cells:
        # The cells a cube of that resolution would have, spread over the box with cubic
        # cells: a flat or long box gets finer cells along its long sides for the same cost.
        cell = math.prod(sides) ** (1 / 3) / (per_pixel - 1)
        wanted = round(extent / cell) + 1
        if wanted != per_pixel:
            reason += (f"; the box is not a cube ({' × '.join(f'{side:.2f}' for side in sides)}): the "
                       f"{(per_pixel - 1) ** 3:,} cells of a {per_pixel}-vertex cube, spread over it as cubic "
                       f"cells of {cell:.4f}, give {wanted} vertices along its longest side")
    clamped = max(MIN_RESOLUTION, min(most, wanted))
    if clamped != wanted:
        reason += f" (clamped to [{MIN_RESOLUTION}, {most}])"
    return clamped, reason


def auto_config(base: TrainConfig, split: DatasetSplit, box: SceneBounds, profile: dict | None,
                user_set: frozenset[str] = frozenset(),
                budget_seconds: float | None = None) -> tuple[TrainConfig, dict]:
    """``base`` (the fast preset, with the user's ``--set`` changes) adjusted to the scene and
    to the run's time budget (None: none), and the decisions with reasons. A setting in
    ``user_set`` (dotted keys given with ``--set``) is the user's: auto keeps it and records
    what it would have chosen."""
    decisions: dict[str, dict] = {}

    def choose(name: str, key: str, chosen, reason: str, **details):
        value, decisions[name] = decide(key, chosen, reason, base, user_set, **details)
        return value

    model = choose("model", "model", MODEL, MODEL_REASON)
    rays = choose("rays", "rays_per_batch", *((RAYS_PER_STEP, RAYS_REASON) if model == MODEL else (
        base.rays_per_batch, f"the preset's: {RAYS_PER_STEP} was measured for the factorised grids only")))

    if profile is not None and isinstance(profile.get("view_dependent"), bool):
        dependent = profile["view_dependent"]
        reason = ("the scene has view-dependent materials" if dependent
                  else "every material is diffuse: colour needs no viewing direction")
    else:
        dependent = base.grid.view_dependent
        reason = "the dataset does not say whether its materials are view-dependent: keep direction input"
    view_dependent = choose("view_dependence", "grid.view_dependent", dependent, reason)

    footprint = pixel_footprint(split, box)
    sides = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))
    extent = max(sides)
    most, most_reason = finest_resolution(budget_seconds)
    clamped, reason = pixel_resolution(footprint, sides, base.grid.cubic_cells, most)
    vertices = vertices_for(clamped, sides) if base.grid.cubic_cells else (clamped,) * 3
    resolution = choose("grid_resolution", "grid.resolution", clamped,
                        reason + f"; vertices per axis {vertices[0]}×{vertices[1]}×{vertices[2]}; {most_reason}",
                        vertices=list(vertices))
    initial = min(base.grid.initial_resolution, resolution)
    schedule = base.grid.upsample_iterations if resolution > initial else ()
    last_growth_min_steps = choose(
        "last_growth", "grid.last_growth_min_steps", LAST_GROWTH_MIN_STEPS if schedule else 0,
        (f"under a time budget the grid grows to its final {resolution} vertices only with {LAST_GROWTH_MIN_STEPS} "
         "steps left at the run's rate so far (a finer grid needs steps to fill in), else it stays one growth "
         "coarser; without a budget it always grows" if schedule else "the grid does not grow"))

    transparent = bool((split.rgba[..., 3] < 255).any())
    random_background = choose(
        "background", "random_background", transparent,
        ("the images have an alpha channel with transparent pixels (transparent film): random background "
         "colours, the alpha as mask" if transparent
         else "every pixel is opaque, so there is no background to separate: background is scene content"))

    has_prior = profile is not None and isinstance(profile.get("occupancy_prior"), dict)
    prior = choose(
        "occupancy_prior", "occupancy_prior", PRIOR_KIND if has_prior else "none",
        (f"the dataset holds Blender's geometry voxelised ({PRIOR_KIND}): empty space is skipped from the first step"
         if has_prior else "the dataset has no occupancy prior: empty space is found from the field's own density"))

    fit_box_at = choose("box_fit", "fit_box_at", *_box_fit(profile, schedule, base.grid.cubic_cells, footprint))
    grid = dataclasses.replace(base.grid, resolution=resolution, initial_resolution=initial,
                               upsample_iterations=schedule, view_dependent=view_dependent,
                               last_growth_min_steps=last_growth_min_steps, finest_cell=footprint)
    config = base.with_settings(preset="auto", model=model, rays_per_batch=rays, grid=grid,
                                random_background=random_background,
                                occupancy_prior=prior, fit_box_at=fit_box_at)
    diagonal = math.sqrt(sum(side ** 2 for side in sides))
    decisions["samples"] = {
        "value": math.ceil(diagonal / (extent / (resolution - 1) * config.grid_step_ratio)) + 1,
        "reason": "one march step per grid cell along the box's diagonal; empty cells are skipped",
    }
    return config, decisions


def _box_fit(profile: dict | None, schedule: tuple[int, ...], cubic_cells: bool, footprint: float) -> tuple[int, str]:
    """``fit_box_at`` and why: the first growth where the box is a guess (no Blender bounds)."""
    if profile is not None and profile.get("bounds") is not None:
        return 0, "the box is the scene's own bounds (scene_profile.json): it stays"
    if not (schedule and cubic_cells):
        return 0, "the grid does not grow (or has no cubic cells): its box stays"
    return schedule[0], (
        f"the box is a guess (no scene bounds in the dataset): at the first growth (scheduled step {schedule[0]}) "
        f"the grids narrow to the box around the pieces of what the field has filled (floaters left out), if that "
        f"keeps at most {FIT_MAX_KEPT:.0%} of the volume, with as many cells as before, so their cells shrink with "
        f"it (not below the pixel footprint, {footprint:.4f}); after each later growth, again, where the finer "
        f"grid's occupancy keeps at most {REFIT_MAX_KEPT:.0%} of the box")
