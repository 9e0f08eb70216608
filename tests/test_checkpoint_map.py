"""A checkpoint read through a memory map (``RunFolder.load_checkpoint(mapped=True)``, what
rendering and `eval` use) holds the same data as one read whole, and the run can still save
over it while the mapped copy is alive (training beside a render of its last checkpoint)."""

from __future__ import annotations

import pickle
import shutil
from pathlib import Path

import pytest
import torch

from nerf_backend.core.errors import NerfError
from nerf_backend.data.run_folder import RunFolder


def _state(seed: int) -> dict:
    generator = torch.Generator().manual_seed(seed)
    return {"iteration": seed, "model": {"grid": torch.randn(64, 33, generator=generator),
                                         "steps": torch.arange(7)},
            "optimizer": {"state": {0: {"exp_avg": torch.randn(1000, generator=generator)}}}}


def test_a_mapped_checkpoint_holds_the_same_data_and_the_run_can_save_over_it(tmp_path):
    run = RunFolder(tmp_path / "run")
    run.path.mkdir()
    run.save_checkpoint(_state(3))
    whole, mapped = run.load_checkpoint(torch.device("cpu")), run.load_checkpoint(torch.device("cpu"), mapped=True)
    assert mapped["iteration"] == whole["iteration"] == 3
    for name, tensor in whole["model"].items():
        assert torch.equal(mapped["model"][name], tensor) and mapped["model"][name].dtype == tensor.dtype
    assert torch.equal(mapped["optimizer"]["state"][0]["exp_avg"], whole["optimizer"]["state"][0]["exp_avg"])
    run.save_checkpoint(_state(4))  # replaced while the mapped one is alive: that one keeps its data
    assert torch.equal(mapped["model"]["grid"], whole["model"]["grid"])
    assert run.load_checkpoint(torch.device("cpu"), mapped=True)["iteration"] == 4


@pytest.mark.parametrize("content", [b"", b"not a checkpoint", pickle.dumps({"iteration": 1})[:5]])
def test_a_damaged_checkpoint_read_through_a_map_is_one_clear_error(tmp_path, content):
    run = RunFolder(tmp_path / "run")
    run.path.mkdir()
    run.checkpoint_path.write_bytes(content)
    with pytest.raises(NerfError, match="checkpoint"):
        run.load_checkpoint(torch.device("cpu"), mapped=True)


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads the process's mappings from /proc")
def test_a_loaded_model_holds_no_map_of_its_checkpoint(trained_marched_run, tmp_path):
    """The map lives only while the model's tensors are copied out of it. On Windows a file
    that is mapped cannot be replaced, so a viewer keeping its model's map would make training's
    next checkpoint fail there; here (Linux) the process's mappings show none is kept, after
    loading the model and after asking whether renders are current."""
    from nerf_backend.evaluation.inference import RENDERS_RECORD, load_trained_model, renders_are_current

    run = RunFolder(tmp_path / "run")
    shutil.copytree(trained_marched_run, run.path)
    run.renders_dir("test").mkdir(parents=True, exist_ok=True)
    (run.renders_dir("test") / RENDERS_RECORD).write_text('{"iteration": 300}')
    checkpoint = str(run.checkpoint_path.resolve())

    def maps_of_checkpoint() -> list[str]:
        return [line for line in Path("/proc/self/maps").read_text().splitlines() if line.endswith(checkpoint)]

    model, _, info = load_trained_model(run, torch.device("cpu"))
    assert info["iteration"] == 300 and maps_of_checkpoint() == []
    assert renders_are_current(run, "test") and maps_of_checkpoint() == []
    state = run.load_checkpoint(torch.device("cpu"), mapped=True)  # the check itself sees a live map
    assert len(maps_of_checkpoint()) >= 1 and state["iteration"] == 300
