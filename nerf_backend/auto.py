"""The ``auto`` preset: the fast model, shaped by what the scene needs.

Blender knows the scene, and the dataset carries that knowledge (``scene_profile.json``)
along with the images. Each decision is returned with its reason and recorded in the
run's ``config.json``:

- bounds: the scene's box (from the profile) limits every ray and the grids;
- view dependence: no glossy, metallic, specular, transmissive, clearcoat or sheen material
  → colour takes no direction input;
- detail: the grid needs no vertex finer than the footprint of a pixel on the scene
  (Nyquist for the training images), so its resolution is the box size over that footprint;
- samples: one march step per grid cell covers the depth range at that same detail;
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

from .config import TrainConfig
from .dataset import DatasetSplit, SceneBounds

MIN_RESOLUTION, MAX_RESOLUTION = 32, 256
# Which of the prior's fills auto uses (measured with bench: see the README).
PRIOR_KIND = "surface"


def pixel_footprint(split: DatasetSplit, box: SceneBounds) -> float:
    """Mean size (world units) of one pixel at the box's centre, over the training cameras."""
    centre = (torch.tensor(box.box_min) + torch.tensor(box.box_max)) / 2
    distances = (split.poses[:, :3, 3] - centre).norm(dim=-1)
    focal = (split.intrinsics.fl_x + split.intrinsics.fl_y) / 2
    return float(distances.mean()) / focal


def auto_config(base: TrainConfig, split: DatasetSplit, box: SceneBounds, profile: dict | None) -> tuple[TrainConfig, dict]:
    """``base`` (the fast preset) adjusted to the scene, and the decisions with reasons."""
    decisions: dict[str, dict] = {}

    view_dependent = base.grid.view_dependent
    if profile is not None and isinstance(profile.get("view_dependent"), bool):
        view_dependent = profile["view_dependent"]
        reason = ("the scene has view-dependent materials" if view_dependent
                  else "every material is diffuse: colour needs no viewing direction")
    else:
        reason = "the dataset does not say whether its materials are view-dependent: keep direction input"
    decisions["view_dependence"] = {"value": view_dependent, "reason": reason}

    footprint = pixel_footprint(split, box)
    extent = max(hi - lo for lo, hi in zip(box.box_min, box.box_max))
    wanted = math.ceil(extent / footprint) + 1
    resolution = max(MIN_RESOLUTION, min(MAX_RESOLUTION, wanted))
    initial = min(base.grid.initial_resolution, resolution)
    decisions["grid_resolution"] = {
        "value": resolution,
        "reason": (f"a pixel covers {footprint:.4f} units at the scene's centre and the box is {extent:.3f} "
                   f"across: {wanted} vertices a side resolve every pixel"
                   + (f" (clamped to [{MIN_RESOLUTION}, {MAX_RESOLUTION}])" if wanted != resolution else "")),
    }
    schedule = base.grid.upsample_iterations if resolution > initial else ()

    alpha = split.rgba[..., 3]
    transparent = bool((alpha < 255).any())
    decisions["background"] = {
        "value": "random colours, alpha as mask" if transparent else "opaque images: background is scene content",
        "reason": ("the images have an alpha channel with transparent pixels (transparent film)" if transparent
                   else "every pixel is opaque, so there is no background to separate"),
    }
    prior = PRIOR_KIND if profile is not None and isinstance(profile.get("occupancy_prior"), dict) else "none"
    decisions["occupancy_prior"] = {
        "value": prior,
        "reason": (f"the dataset holds Blender's geometry voxelised ({PRIOR_KIND}): empty space is skipped "
                   "from the first step" if prior != "none" else
                   "the dataset has no occupancy prior: empty space is found from the field's own density"),
    }
    grid = dataclasses.replace(base.grid, resolution=resolution, initial_resolution=initial,
                               upsample_iterations=schedule, view_dependent=view_dependent)
    config = dataclasses.replace(base, preset="auto", grid=grid, grid_step_ratio=1.0, random_background=transparent,
                                 occupancy_prior=prior)
    diagonal = math.sqrt(sum((hi - lo) ** 2 for lo, hi in zip(box.box_min, box.box_max)))
    decisions["samples"] = {
        "value": math.ceil(diagonal / (extent / (resolution - 1))) + 1,
        "reason": "one march step per grid cell along the box's diagonal; empty cells are skipped",
    }
    return config, decisions
