"""Validation and checkpoints pause the training at most ``pause_share`` of its time each, and a
checkpoint written behind the training is whole on disk before its event and the run's end."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from nerf_backend.core.errors import NerfError
from nerf_backend.data.run_folder import RunFolder
from nerf_backend.training.checkpoint_writer import CheckpointWriter
from nerf_backend.training.trainer import TrainOptions, train
from nerf_contract import training_events as events

STEPS = 40


def _events(dataset: Path, run: Path, share: float) -> list:
    train(TrainOptions(dataset=dataset, run=run, preset="fast", iterations=STEPS, progress=False,
                       overrides=("validate_every=1", "checkpoint_every=1", f"pause_share={share}")))
    return RunFolder(run).read_events()


def test_pauses_on_every_step_without_a_share_and_spaced_with_one(tiny_demo_dataset, tmp_path):
    every = _events(tiny_demo_dataset, tmp_path / "every", 0.0)
    spaced = _events(tiny_demo_dataset, tmp_path / "spaced", 0.02)
    for found in (every, spaced):
        kinds = [e.KIND for e in found]
        # The run's last checkpoint is written, and its event logged, before the run's end.
        assert kinds[-1] == "done" and kinds[-2] == "checkpoint" and found[-2].iteration == STEPS
    count = {name: {kind: sum(e.KIND == kind for e in found) for kind in ("val", "checkpoint")}
             for name, found in (("every", every), ("spaced", spaced))}
    # Every step, and the run's end once more (the final checkpoint; the final validation is
    # the last step's own).
    assert count["every"] == {"val": STEPS, "checkpoint": STEPS + 1}
    # Spaced by 50 times their own length: a tiny model's step is not 50 times a view's render
    # or a checkpoint's serialising, so most points pass.
    assert 1 <= count["spaced"]["val"] <= STEPS // 2 and 2 <= count["spaced"]["checkpoint"] <= STEPS // 2
    assert RunFolder(tmp_path / "spaced").load_checkpoint(torch.device("cpu"))["iteration"] == STEPS


def test_a_failed_background_write_is_raised_in_the_training_and_logs_nothing(tmp_path):
    run = RunFolder(tmp_path / "run")
    writer = CheckpointWriter(run)
    writer.save({"iteration": 1}, events.Checkpoint(iteration=1))
    writer.finish()
    assert run.load_checkpoint(torch.device("cpu"))["iteration"] == 1
    blocked = RunFolder(tmp_path / "blocked")  # its checkpoint's name taken by a folder: the move fails
    (blocked.checkpoint_path / "kept").mkdir(parents=True)
    writer = CheckpointWriter(blocked)
    writer.save({"iteration": 2}, events.Checkpoint(iteration=2))
    with pytest.raises(NerfError, match=r"checkpoint\.pt: cannot write \("):
        writer.finish()
    assert (blocked.checkpoint_path / "kept").is_dir() and not list(blocked.path.glob(".*.tmp"))
    assert not blocked.events_path.exists()  # no event for the write that failed
    writer.finish()  # raised once
