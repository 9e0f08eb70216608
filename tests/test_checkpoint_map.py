"""A checkpoint read through a memory map (``RunFolder.load_checkpoint(mapped=True)``, what
rendering and `eval` use) holds the same data as one read whole, and the run can still save
over it while the mapped copy is alive (training beside a render of its last checkpoint)."""

from __future__ import annotations

import pickle

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
