"""Every preset planned, without training, on the demo dataset (Blender's scene profile, bounds
and occupancy prior) and on a foreign one (the same views without them): each decision checked,
the whole plan in config.json, a resumed run's plan kept, and the trainer writing what was planned."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest

from nerf_backend.configs.presets import PRESETS
from nerf_backend.configs.train_config import TrainConfig
from nerf_backend.core.errors import NerfError, RunError
from nerf_backend.data.dataset import load_scene_bounds
from nerf_backend.data.run_folder import RunFolder
from nerf_backend.model_components.ray_bounds import BOX_PADDING, PROTOCOL_BOX
from nerf_backend.models.registry import model_class
from nerf_backend.planning.facts import RunRequest, gather_facts, starting_settings
from nerf_backend.planning.footprint import MAX_RESOLUTION, MIN_RESOLUTION, pixel_footprint
from nerf_backend.planning.plan import plan_run
from nerf_backend.planning.rules import GPU_RAYS_PER_STEP, LAST_GROWTH_MIN_STEPS, RAYS_PER_STEP, RULES
from nerf_backend.training.trainer import TrainOptions, train

BUDGET = 120.0
# Blender's own files in a dataset; a foreign dataset (another tool's) has none of them.
BLENDER_FILES = ("scene_profile.json", "occupancy_prior.npz", "scene_geometry.ply")


@pytest.fixture(scope="module")
def foreign_dataset(tiny_demo_dataset, tmp_path_factory):
    """The demo's views as another tool would give them: no profile, bounds or prior."""
    folder = tmp_path_factory.mktemp("foreign") / "dataset"
    shutil.copytree(tiny_demo_dataset, folder, ignore=shutil.ignore_patterns(*BLENDER_FILES))
    return folder


def _plan(dataset, tmp_path, **request):
    facts = gather_facts(dataset, RunFolder(tmp_path / "run"), RunRequest(device="cpu", **request))
    return facts, plan_run(facts, RULES)


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("kind", ["demo", "foreign"])
def test_each_preset_is_planned_whole_with_a_reason_for_every_decision(preset, kind, tiny_demo_dataset,
                                                                       foreign_dataset, tmp_path):
    dataset = tiny_demo_dataset if kind == "demo" else foreign_dataset
    facts, plan = _plan(dataset, tmp_path, preset=preset, max_seconds=BUDGET)
    record = json.loads(json.dumps(plan.record()))  # config.json: JSON, whole
    assert TrainConfig.from_dict(record["config"]) == plan.config
    decisions = record["decisions"]
    for name, decision in decisions.items():
        assert "value" in decision and decision["reason"].strip(), name
    # Every start: the device, the budget, the views, the rays' bounds, the prior, the images.
    assert (record["device"], decisions["device"]["reason"]) == ("cpu", "asked for with --device cpu")
    assert (plan.max_seconds, plan.stop_at_iterations) == (BUDGET, False)
    assert plan.schedule_seconds == (None if plan.config.schedule == "iterations" else BUDGET)
    assert record["train_views"] == decisions["train_views"]["value"] == len(facts.train_split) == 30
    assert record["image_size"] == [40, 40]
    bounds = decisions["ray_bounds"]["value"]
    if plan.config.ray_bounds == "scene":
        box = load_scene_bounds(dataset).padded(BOX_PADDING) if kind == "demo" else PROTOCOL_BOX
        assert bounds == {"kind": "scene_box", "box_min": list(box.box_min), "box_max": list(box.box_max)}
    else:
        assert bounds == {"kind": "protocol", "near": 2.0, "far": 6.0}
    uses_prior = model_class(plan.config.model).uses_occupancy_prior and plan.config.occupancy_prior != "none"
    assert plan.prior_kind == decisions["prior_kind"]["value"] == ("solid" if uses_prior and kind == "demo" else None)
    assert decisions["coarse_images"]["value"] == (
        pixel_footprint(facts.train_split, plan.ray_bounds.box) if plan.config.coarse_images else None)
    _check_shaping(preset, kind, facts, plan)


def _check_shaping(preset, kind, facts, plan):
    """What the rules that shape a preset to the scene decided, and nothing where none applies."""
    config, decisions = plan.config, plan.decisions
    shaped = {"auto": {"model", "rays", "view_dependence", "colour", "region_appearance", "refraction", "grid_resolution",
                       "finest_cell", "initial_resolution", "growth", "last_growth", "background", "occupancy_prior",
                       "box_fit", "samples"} | ({"reflection_frequencies"} if config.grid.region_appearance else set()),
              "surface": {"surface_softness", "surface_opacity"},
              "plenoxels": {"grid_resolution", "finest_cell", "initial_resolution", "box_fit"}}.get(preset, set())
    every_start = {"device", "max_seconds", "stop_at_iterations", "schedule_seconds", "train_views", "ray_bounds",
                   "prior_kind", "coarse_images"}
    assert set(decisions) == every_start | shaped
    if preset == "auto":
        assert (config.model, config.rays_per_batch) == ("grid", RAYS_PER_STEP)
        # The demo's profile says A.blend has view-dependent materials; a foreign dataset says nothing.
        assert config.grid.view_dependent is True
        assert "view-dependent materials" in decisions["view_dependence"]["reason"] if kind == "demo" else (
            "does not say" in decisions["view_dependence"]["reason"])
        assert config.grid.deferred_colour is True and "once a ray" in decisions["colour"]["reason"]
        # The demo's gold sphere is metal, but too little of it; a foreign dataset says nothing.
        assert config.grid.region_appearance is False
        assert ("are metal or thin film, under" if kind == "demo" else "does not say") in decisions["region_appearance"]["reason"]
        assert MIN_RESOLUTION <= config.grid.resolution <= MAX_RESOLUTION
        assert config.grid.finest_cell == pytest.approx(pixel_footprint(facts.train_split, plan.ray_bounds.box))
        assert config.grid.last_growth_min_steps == (LAST_GROWTH_MIN_STEPS if config.grid.upsample_iterations else 0)
        assert config.random_background is True  # the demo's film is transparent
        assert config.occupancy_prior == ("solid" if kind == "demo" else "none")
        # Blender's bounds are the scene's; without them the box is a guess, narrowed at the first
        # growth (40×40 pixels on nerf_synthetic's box ask for no finer grid than the first: none).
        growths = config.grid.upsample_iterations
        assert config.fit_box_at == (growths[0] if kind == "foreign" and growths else 0)
        if kind == "foreign" and not growths:
            assert "does not grow" in decisions["box_fit"]["reason"]
    if preset == "surface":
        assert config.surface.final_beta_cells == 0.5  # 40×40: a pixel covers several cells
        # NeuS where Blender's prior bounds the surface, VolSDF without one.
        assert config.surface.opacity == ("neus" if kind == "demo" else "volsdf")
    if preset == "plenoxels":
        grid = config.plenoxels
        assert MIN_RESOLUTION <= grid.resolution <= MAX_RESOLUTION
        assert grid.initial_resolution == max(MIN_RESOLUTION, grid.resolution // 2)
        grown = grid.resolution > grid.initial_resolution and grid.upsample_iterations
        assert config.fit_box_at == (grid.upsample_iterations[0] if kind == "foreign" and grown else 0)
    if not shaped:
        assert config == PRESETS[preset]  # no rule reshapes it


def test_the_users_set_wins_and_the_plan_says_what_the_rule_would_have_chosen(tiny_demo_dataset, tmp_path):
    _, plan = _plan(tiny_demo_dataset, tmp_path, preset="auto", overrides=("rays_per_batch=512", "model=plenoxels"))
    assert (plan.config.rays_per_batch, plan.config.model) == (512, "plenoxels")
    assert plan.decisions["model"]["reason"].startswith("set with --set model; the rule would choose 'grid'")
    assert "plenoxels.resolution" not in plan.decisions and "initial_resolution" in plan.decisions  # its own grid's


def test_auto_takes_more_rays_a_step_on_cuda_and_the_users_count_still_wins(tiny_demo_dataset, tmp_path):
    """A GPU's step is bound by its kernel launches: 8 192 rays on CUDA (lego on an H200:
    docs/benchmarks_lego.md), the CPU's 2 048 elsewhere; the user's --set wins on either."""
    facts, on_cpu = _plan(tiny_demo_dataset, tmp_path, preset="auto")

    def on_cuda(*overrides: str):
        request = RunRequest(device="cuda", preset="auto", overrides=overrides)
        return plan_run(dataclasses.replace(facts, request=request, start=starting_settings(request, None),
                                            devices=("cuda", "cpu")), RULES)

    plan = on_cuda()
    assert on_cpu.config.rays_per_batch == RAYS_PER_STEP == 2048
    assert plan.device.type == "cuda" and plan.config.rays_per_batch == GPU_RAYS_PER_STEP == 8192
    assert plan.decisions["rays"]["reason"].startswith("on CUDA") and "H200" in plan.decisions["rays"]["reason"]
    assert on_cuda("rays_per_batch=1024").config.rays_per_batch == 1024


@pytest.mark.parametrize("minutes", [10, 29.9, 30, 60])
def test_auto_defers_colour_at_every_budget(tiny_demo_dataset, tmp_path, minutes):
    """lego at 800×800: deferred colour 0.51 dB ahead after 10 minutes and, with the grid's
    compiled lit pass, 0.11 dB ahead after 30 (docs/benchmarks_lego.md, "Deferred colour")."""
    _, plan = _plan(tiny_demo_dataset, tmp_path / str(minutes), preset="auto", max_seconds=60.0 * minutes)
    decision = plan.decisions["colour"]
    assert plan.config.grid.deferred_colour is True and decision["value"] is True
    assert "once a ray" in decision["reason"] and "after 30 minutes" in decision["reason"]


def test_a_budget_and_views_are_planned_from_the_request(tiny_demo_dataset, tmp_path):
    _, plan = _plan(tiny_demo_dataset, tmp_path, preset="fast", iterations=50, overrides=("max_train_views=10",))
    assert (plan.config.iterations, plan.stop_at_iterations, plan.max_seconds) == (50, True, None)
    assert plan.train_views == 10 and "the first 10 of 30" in plan.decisions["train_views"]["reason"]


def test_bad_requests_are_refused_before_any_plan(tiny_demo_dataset, foreign_dataset, tmp_path):
    with pytest.raises(NerfError, match="--device quantum: choose auto, cpu, cuda or mps"):
        plan_run(gather_facts(tiny_demo_dataset, RunFolder(tmp_path / "r"), RunRequest(device="quantum")), RULES)
    with pytest.raises(NerfError, match="occupancy_prior=solid asked for, but the dataset has no occupancy prior"):
        _plan(foreign_dataset, tmp_path, preset="fast", overrides=("occupancy_prior=solid",))
    with pytest.raises(NerfError, match="schedule 'weekly': choose budget or iterations"):
        _plan(tiny_demo_dataset, tmp_path, preset="fast", overrides=("schedule=weekly",))


def test_a_resumed_run_keeps_its_plan_and_takes_a_new_budget(tiny_demo_dataset, tmp_path):
    _, plan = _plan(tiny_demo_dataset, tmp_path, preset="auto", max_seconds=BUDGET)
    run = RunFolder(tmp_path / "run")
    run.path.mkdir()
    run.write_config(plan.record())
    _, resumed = _plan(tiny_demo_dataset, tmp_path, resume=True, max_seconds=2 * BUDGET)
    assert resumed.config == plan.config and resumed.seed == plan.seed
    assert {name: resumed.decisions[name] for name in ("grid_resolution", "box_fit", "model")} == {
        name: plan.decisions[name] for name in ("grid_resolution", "box_fit", "model")}
    assert (resumed.max_seconds, resumed.schedule_seconds) == (2 * BUDGET, 2 * BUDGET)
    with pytest.raises(RunError, match="run was trained with preset 'auto', not 'fast'"):
        _plan(tiny_demo_dataset, tmp_path, resume=True, preset="fast")
    with pytest.raises(RunError, match="--set applies to new runs"):
        _plan(tiny_demo_dataset, tmp_path, resume=True, overrides=("rays_per_batch=1",))


def test_the_trainer_writes_the_plan_it_runs(tiny_demo_dataset, tmp_path):
    """config.json after a real (short) run is the plan made without training."""
    _, plan = _plan(tiny_demo_dataset, tmp_path, preset="auto", iterations=3)
    train(TrainOptions(dataset=tiny_demo_dataset, run=tmp_path / "trained", preset="auto", iterations=3,
                       device="cpu", progress=False, validate=False))
    written = json.loads((tmp_path / "trained" / "config.json").read_text())
    assert written == json.loads(json.dumps(plan.record()))
