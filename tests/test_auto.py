"""The rules that shape a preset to the scene (planning/rules.py: auto's, the surface and
plenoxels presets'), from a scene profile and the training images (no rendering): each applied
to a plan whose box is given as is (the planner pads the scene's own by 5 %)."""

from __future__ import annotations

from pathlib import Path

import torch

from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.cameras import Intrinsics
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.data.dataset import DatasetSplit
from nerf_backend.model_components.ray_bounds import RayBounds
from nerf_backend.planning.facts import RunFacts, RunRequest, starting_settings
from nerf_backend.planning.plan import RunPlan, apply_rules
from nerf_backend.planning.rules import RULES, auto_model, sparse_grid_box_fit, surface_opacity

BOX = SceneBounds((-1.0, -1.0, -0.25), (1.0, 1.0, 0.25))


def _split(opaque: bool = False) -> DatasetSplit:
    """Four 100×100 views at radius 4 with a transparent border unless ``opaque``."""
    rgba = torch.full((4, 100, 100, 4), 255, dtype=torch.uint8)
    if not opaque:
        rgba[:, :10, :, 3] = 0
    poses = torch.eye(4).repeat(4, 1, 1)
    poses[:, 2, 3] = 4.0
    return DatasetSplit("train", Intrinsics(100, 100, 138.9, 138.9, 50.0, 50.0), poses, rgba, [])


PROFILE = {"view_dependent": False, "occupancy_prior": {"file": "occupancy_prior.npz"}}
# The rules that shape a new run's preset (those from auto's to the plenoxels grid's).
SHAPING = RULES[RULES.index(auto_model):RULES.index(sparse_grid_box_fit) + 1]


def _shaped(preset="auto", split=None, box=BOX, profile=PROFILE, overrides=(), budget=None, priors=None,
            prior_kind=None, rules=SHAPING):
    """``preset``'s config with the user's ``overrides`` after ``rules``, and the decisions."""
    split = split if split is not None else _split()
    request = RunRequest(preset=preset, overrides=tuple(overrides), max_seconds=budget)
    facts = RunFacts(request, starting_settings(request, None), Path("d"), split, profile, box, priors or {}, ("cpu",))
    plan = RunPlan(config=facts.start, ray_bounds=RayBounds(box=box),
                   schedule_seconds=budget, train_views=len(split), prior_kind=prior_kind)
    plan = apply_rules(facts, plan, rules)
    return plan.config, plan.decisions


def test_auto_reads_the_scene():
    config, decisions = _shaped()
    assert config.grid.view_dependent is False and "diffuse" in decisions["view_dependence"]["reason"]
    assert config.occupancy_prior == "solid" and "first step" in decisions["occupancy_prior"]["reason"]
    assert config.random_background is True
    # A pixel covers 4 / 138.9 = 0.0288 units: 71 vertices a side for a 2-unit cube. The box
    # is 2 × 2 × 0.5, so the cube's 70³ cells become cubic cells of (2·2·0.5)^(1/3) / 70 =
    # 0.0180 units: 112 vertices along the long sides, 29 along the short one.
    assert config.grid.resolution == 112
    assert decisions["grid_resolution"]["vertices"] == [112, 112, 29]
    assert "343,000 cells of a 71-vertex cube" in decisions["grid_resolution"]["reason"]
    # The box narrows to the scene once, at the first growth; cells not finer than a pixel.
    assert config.fit_box_at == PRESETS["auto"].grid.upsample_iterations[0] == decisions["box_fit"]["value"]
    assert abs(config.grid.finest_cell - 4 / 138.9) < 1e-4


def test_the_box_is_fitted_only_where_it_is_a_guess():
    """Blender's bounds are the scene's: kept. Without them the box is nerf_synthetic's guess,
    narrowed once the field shows where the scene is."""
    bounded = {**PROFILE, "bounds": {"min": list(BOX.box_min), "max": list(BOX.box_max)}}
    config, decisions = _shaped(profile=bounded)
    assert config.fit_box_at == 0 and "scene's own bounds" in decisions["box_fit"]["reason"]
    config, decisions = _shaped(profile=None)
    assert config.fit_box_at == PRESETS["auto"].grid.upsample_iterations[0]
    assert "a guess" in decisions["box_fit"]["reason"]


def test_auto_without_a_profile_keeps_the_safe_choices():
    config, decisions = _shaped(split=_split(opaque=True), profile=None)
    assert config.grid.view_dependent is True
    assert config.occupancy_prior == "none" and "no occupancy prior" in decisions["occupancy_prior"]["reason"]
    assert config.random_background is False


def test_settings_given_with_set_are_the_users():
    assignments = ["occupancy_prior=none", "grid.resolution=40", "grid.view_dependent=true"]
    config, decisions = _shaped(overrides=assignments)
    assert (config.occupancy_prior, config.grid.resolution, config.grid.view_dependent) == ("none", 40, True)
    assert decisions["occupancy_prior"]["reason"].startswith("set with --set occupancy_prior; the rule would choose 'solid'")
    assert decisions["grid_resolution"]["value"] == 40
    # What was not set is still decided.
    assert config.random_background is True and "random background" in decisions["background"]["reason"]


def test_the_surface_presets_final_softness_follows_the_pixel():
    """Where a pixel is finer than the grid's cells (800×800) the surface preset's final β is
    sharper, a quarter cell; where it is coarser (100×100) it stays at half a cell; a value the
    user set is kept, with what the rule would have chosen."""
    from nerf_backend.core.cameras import Intrinsics
    surface = PRESETS["surface"]
    coarse = _split()
    config, decision = _shaped("surface", coarse)
    assert config.surface.final_beta_cells == 0.5 and "a pixel covers" in decision["surface_softness"]["reason"]
    fine = DatasetSplit("train", Intrinsics(800, 800, 8 * 138.9, 8 * 138.9, 400.0, 400.0), coarse.poses,
                        torch.zeros((4, 800, 800, 4), dtype=torch.uint8), [])
    config, decision = _shaped("surface", fine)
    assert config.surface.final_beta_cells == 0.25 == decision["surface_softness"]["value"]
    assert config.surface.resolution == surface.surface.resolution  # nothing else changes
    config, decision = _shaped("surface", fine, overrides=["surface.final_beta_cells=0.4"])
    assert config.surface.final_beta_cells == 0.4
    assert decision["surface_softness"]["reason"].startswith("set with --set surface.final_beta_cells; the rule would choose 0.25")


def _opacity(prior, overrides=()):
    """The surface preset's opacity with the dataset's ``prior`` (of its kind) given to the model."""
    kind = None if prior is None else prior.kind
    return _shaped("surface", overrides=overrides, priors={} if prior is None else {kind: prior}, prior_kind=kind,
                   rules=(surface_opacity,))


def test_the_surface_presets_opacity_is_neus_only_where_the_prior_bounds_the_surface():
    """NeuS where Blender's prior bounds the surface to a band (a solid prior with its surface
    cells), VolSDF where nothing does (no prior, a prior without surface cells, or the band
    turned off); a value the user set is kept, with what the rule would have chosen."""
    from nerf_backend.data.occupancy_prior import OccupancyPrior
    surface = PRESETS["surface"]
    solid = torch.zeros((8, 8, 8), dtype=torch.bool)
    solid[2:6, 2:6, 2:6] = True
    shell = solid.clone()
    shell[3:5, 3:5, 3:5] = False
    bounded = OccupancyPrior(solid, (-1.0, -1.0, -1.0), 0.25, "solid", 1, shell)
    config, decision = _opacity(bounded)
    assert config.surface.opacity == "neus" == decision["surface_opacity"]["value"]
    assert "bounds the surface to a band" in decision["surface_opacity"]["reason"]
    assert config.surface.final_beta_cells == surface.surface.final_beta_cells  # nothing else changes
    for prior, overrides in ((None, ()), (OccupancyPrior(solid, (-1.0,) * 3, 0.25, "solid", 1), ()),
                             (OccupancyPrior(shell, (-1.0,) * 3, 0.25, "surface", 1, shell), ()),
                             (bounded, ("surface.prior_band=false",))):
        config, decision = _opacity(prior, overrides)
        assert config.surface.opacity == "volsdf" and "no prior bounds the surface" in decision["surface_opacity"]["reason"]
    config, decision = _opacity(bounded, ("surface.opacity=volsdf",))
    assert config.surface.opacity == "volsdf"
    assert decision["surface_opacity"]["reason"].startswith("set with --set surface.opacity; the rule would choose 'neus'")


def test_auto_trains_the_model_its_measurements_chose_and_says_why():
    """The factorised grids, with the figures that chose them over Plenoxels; a model given with
    --set is the user's, and the record says what auto would have chosen."""
    config, decisions = _shaped()
    assert config.model == decisions["model"]["value"] == "grid"
    assert "plenoxels" in decisions["model"]["reason"] and " dB" in decisions["model"]["reason"]
    config, decisions = _shaped(overrides=["model=plenoxels"])
    assert config.model == "plenoxels" and decisions["model"]["reason"].startswith("set with --set model")


def test_auto_takes_the_rays_a_step_its_measurements_chose_for_the_grids():
    """2 048 rays a step for the factorised grids (measured on lego against 1 024 and 4 096);
    the user's --set wins; another model set with --set keeps its preset's rays."""
    config, decisions = _shaped()
    assert config.rays_per_batch == decisions["rays"]["value"] == 2048 != PRESETS["auto"].rays_per_batch
    assert "lego" in decisions["rays"]["reason"] and " dB" in decisions["rays"]["reason"]
    config, decisions = _shaped(overrides=["rays_per_batch=512"])
    assert config.rays_per_batch == 512 and decisions["rays"]["reason"].startswith("set with --set rays_per_batch")
    config, decisions = _shaped(overrides=["model=plenoxels"])
    assert config.rays_per_batch == PRESETS["auto"].rays_per_batch and "factorised grids only" in decisions["rays"]["reason"]


def test_a_budget_of_thirty_minutes_or_more_grows_a_finer_grid():
    """Where a pixel asks for more vertices than the grids may have, the limit is 256 along the
    longest side, and 384 under a budget of 30 minutes or more (measured on lego: 35.00 dB after
    30 minutes against 256's 34.54, the same after 10); the reason says which and why."""
    cube = SceneBounds((-1.5,) * 3, (1.5,) * 3)
    poses = torch.eye(4).repeat(4, 1, 1)
    poses[:, 2, 3] = 4.0
    fine = DatasetSplit("train", Intrinsics(800, 800, 1111.1, 1111.1, 400.0, 400.0), poses,
                        torch.full((4, 800, 800, 4), 255, dtype=torch.uint8), [])  # a pixel: 0.0036 units
    for budget, vertices in ((None, 256), (600.0, 256), (1799.0, 256), (1800.0, 384), (3600.0, 384)):
        config, decisions = _shaped(split=fine, box=cube, profile=None, budget=budget)
        reason = decisions["grid_resolution"]["reason"]
        assert config.grid.resolution == decisions["grid_resolution"]["value"] == vertices, budget
        assert f"clamped to [32, {vertices}]" in reason and "35.00 dB" in reason
    # A scene whose pixels ask for fewer vertices gets what they ask, whatever the budget.
    for budget in (None, 3600.0):
        assert _shaped(budget=budget)[0].grid.resolution == 112
