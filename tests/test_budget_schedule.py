"""A time budget that shapes the training: under ``--max-seconds`` the preset's schedule
(learning-rate decay, grid growth, centre crops) is laid over the budget, so it ends when the
budget does; ``schedule=iterations`` keeps counting steps (the run is then cut by the clock)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from conftest import run_python
from nerf_backend.configs.presets import PRESETS
from nerf_backend.configs.train_config import TrainConfig

BUDGET_S = 8.0


def test_the_scheduled_step_follows_whichever_budget_ends_the_run():
    config = TrainConfig(preset="x", iterations=3000)
    assert config.scheduled_step(700, None) == 700  # no time budget: steps taken
    assert config.scheduled_step(700, 0.25, stop_at_iterations=False) == 750  # the clock alone
    assert config.scheduled_step(700, 0.1, stop_at_iterations=True) == 700  # steps lead
    assert config.scheduled_step(700, 0.5, stop_at_iterations=True) == 1500  # time leads
    assert config.scheduled_step(10, 1.7, stop_at_iterations=False) == 3000  # overshoot: the end
    assert config.scheduled_step(10, -0.1, stop_at_iterations=False) == 0
    counting = TrainConfig(preset="x", iterations=3000, schedule="iterations")
    assert counting.scheduled_step(700, 0.5, stop_at_iterations=False) == 700


def _events(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / "events.jsonl").read_text().splitlines()]


def _train(dataset: Path, run: Path, *extra: str, budget: float = BUDGET_S) -> tuple[list[dict], dict]:
    run_python("-m", "nerf_backend", "train", str(dataset), "--preset", "fast", "--out", str(run),
               "--max-seconds", str(budget), "--no-progress", "--set", "validate_every=100000", *extra)
    return _events(run), torch.load(run / "checkpoint.pt", weights_only=True)


def test_a_time_budget_lays_the_whole_schedule_over_itself(tiny_demo_dataset, tmp_path):
    """fast's schedule is 3000 steps (decay from 0.02 to 0.002, the grid grown 48 → 128 by
    step 1000). A budget of a few seconds takes far fewer steps on the 40×40 dataset, yet
    under the budget schedule the run ends at the end of its schedule: final learning
    rate, final grid; counted in steps, the same budget ends early in it."""
    fast = PRESETS["fast"]
    events, checkpoint = _train(tiny_demo_dataset, tmp_path / "budget")
    done = events[-1]
    assert done["event"] == "done" and done["reason"] == "time"
    start = events[0]
    assert start["target_iterations"] is None and start["schedule_seconds"] == BUDGET_S
    trains = [e for e in events if e["event"] == "train"]
    steps = done["iteration"]
    assert steps < fast.iterations  # the budget ended it, not the step count
    scheduled = [e["scheduled"] for e in trains]
    assert scheduled == sorted(scheduled) and all(s > e["iteration"] for s, e in zip(scheduled, trains))
    # The last step began at most one step before the budget's end, so its rate (the
    # optimiser's, as checkpointed) is the schedule's that near its end. One step's length is
    # bounded by the longest gap between the logged steps (10 steps apart): on a quiet machine
    # a few hundredths of the budget, more when the machine is loaded (the bound follows).
    elapsed = [e["elapsed_s"] for e in trains]
    longest = max(later - earlier for earlier, later in zip(elapsed, elapsed[1:]))
    reached = int(fast.iterations * (1.0 - longest / BUDGET_S))
    assert reached > fast.iterations // 2, f"steps of {longest:.2f} s: too few for the test to say anything"
    assert checkpoint["optimizer"]["param_groups"][0]["lr"] <= fast.learning_rate_at(reached) * (1 + 1e-6)
    planes = checkpoint["model"]["field.density_grid.planes.0"]
    assert max(planes.shape[-2:]) == fast.grid.resolution  # grown to the end of its schedule

    events, checkpoint = _train(tiny_demo_dataset, tmp_path / "steps", "--set", "schedule=iterations")
    trains = [e for e in events if e["event"] == "train"]
    assert events[-1]["reason"] == "time"
    assert all(e["scheduled"] == e["iteration"] - 1 for e in trains)  # counted in steps
    last_lr = checkpoint["optimizer"]["param_groups"][0]["lr"]
    assert last_lr == pytest.approx(fast.learning_rate_at(events[-1]["iteration"] - 1), rel=1e-6)
    if events[-1]["iteration"] < fast.grid.upsample_iterations[-1]:
        planes = checkpoint["model"]["field.density_grid.planes.0"]
        assert max(planes.shape[-2:]) < fast.grid.resolution  # cut before its grid was grown


def test_with_an_iteration_count_as_well_the_first_to_end_stops_the_run(tiny_demo_dataset, tmp_path):
    events, _ = _train(tiny_demo_dataset, tmp_path / "run", "--iters", "20", budget=120.0)
    assert events[-1]["reason"] == "iterations" and events[-1]["iteration"] == 20
    assert events[0]["target_iterations"] == 20
    # 20 steps end the run long before the budget, so steps lead the schedule.
    assert all(e["scheduled"] == e["iteration"] - 1 for e in events if e["event"] == "train")


def test_an_unknown_schedule_is_a_clear_error(tiny_demo_dataset, tmp_path):
    result = run_python("-m", "nerf_backend", "train", str(tiny_demo_dataset), "--preset", "fast", "--out",
                        str(tmp_path / "run"), "--max-seconds", "5", "--set", "schedule=weekly", check=False)
    assert result.returncode != 0
    assert "schedule 'weekly': choose budget or iterations" in result.stderr
    assert not (tmp_path / "run").exists() or not any((tmp_path / "run").iterdir())


@pytest.mark.parametrize("preset", ["fast", "preview"])
def test_old_runs_keep_their_step_schedule(preset):
    """A config.json from before budget schedules has no "schedule": it counted steps."""
    stored = PRESETS[preset].to_dict()
    del stored["schedule"]
    assert TrainConfig.from_dict(stored).schedule == "iterations"


def test_a_budget_too_short_for_the_final_grid_keeps_it_a_growth_coarser(tiny_demo_dataset, tmp_path):
    """With more steps asked of the last growth than the budget leaves, the run ends on the
    grid one growth short of the final size, says so once, and a resumed run keeps it."""
    fast = PRESETS["fast"]
    held = ("--set", "grid.last_growth_min_steps=1000000")
    run = tmp_path / "run"
    result = run_python("-m", "nerf_backend", "train", str(tiny_demo_dataset), "--preset", "fast", "--out", str(run),
                        "--max-seconds", "4", "--no-progress", "--set", "validate_every=100000", *held)
    penultimate = round(fast.grid.initial_resolution * (fast.grid.resolution / fast.grid.initial_resolution)
                        ** ((len(fast.grid.upsample_iterations) - 1) / len(fast.grid.upsample_iterations)))
    planes = torch.load(run / "checkpoint.pt", weights_only=True)["model"]["field.density_grid.planes.0"]
    assert max(planes.shape[-2:]) == penultimate < fast.grid.resolution
    assert result.stderr.count(f"grid kept at {penultimate} vertices a side, not grown to {fast.grid.resolution}") == 1
    run_python("-m", "nerf_backend", "train", str(tiny_demo_dataset), "--out", str(run), "--resume",
               "--max-seconds", "6", "--no-progress")
    planes = torch.load(run / "checkpoint.pt", weights_only=True)["model"]["field.density_grid.planes.0"]
    assert max(planes.shape[-2:]) == penultimate
