"""``hold-out``: a dataset with one split (nerf_synthetic's public lego training views) made into
train / val / test, every N-th view held out, loadable by the backend; bad input named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from nerf_backend.cli import main
from nerf_backend.data.dataset import load_split
from nerf_backend.data.hold_out import hold_out_indices


def _source(folder: Path, views: int) -> Path:
    (folder / "train").mkdir(parents=True)
    frames = []
    for index in range(views):
        Image.fromarray(np.full((4, 4, 4), index, dtype=np.uint8)).save(folder / "train" / f"r_{index}.png")
        pose = np.eye(4)
        pose[0, 3] = index  # each view's own pose, to follow it into its split
        frames.append({"file_path": f"./train/r_{index}", "rotation": 0.0, "transform_matrix": pose.tolist()})
    (folder / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    return folder


def test_lego_split_is_the_issues():
    """100 views, every 8th held out: 0, 8 ... 96 test (13), 4 and 12 val, 85 train."""
    split = hold_out_indices(100, every=8, val_views=2)
    assert split["test"] == list(range(0, 100, 8)) and split["val"] == [4, 12] and len(split["train"]) == 85
    assert sorted(split["train"] + split["val"] + split["test"]) == list(range(100))


def test_the_split_dataset_loads_with_each_view_where_it_belongs(tmp_path, capsys):
    source = _source(tmp_path / "source", 20)
    assert main(["hold-out", str(source), "--out", str(tmp_path / "split")]) == 0
    assert "15 train, 2 val, 3 test" in capsys.readouterr().out
    for name, indices in hold_out_indices(20, 8, 2).items():
        split = load_split(tmp_path / "split", name)
        assert split.poses[:, 0, 3].tolist() == [float(i) for i in indices]
        assert split.rgba[:, 0, 0, 0].tolist() == indices  # the image went with its pose
    assert (source / "train" / "r_19.png").is_file()  # the source is untouched


def test_bad_input_is_named_and_nothing_is_written(tmp_path, capsys):
    source = _source(tmp_path / "source", 10)
    (source / "train" / "r_3.png").unlink()
    assert main(["hold-out", str(source), "--out", str(tmp_path / "split")]) == 2
    assert "frame 3" in capsys.readouterr().err and not (tmp_path / "split").exists()
    assert main(["hold-out", str(tmp_path / "nowhere"), "--out", str(tmp_path / "split")]) == 2
    assert "transforms_train.json: not found" in capsys.readouterr().err
    (tmp_path / "taken").mkdir()
    _source(tmp_path / "good", 10)
    assert main(["hold-out", str(tmp_path / "good"), "--out", str(tmp_path / "taken")]) == 2
    assert "already exists" in capsys.readouterr().err


@pytest.mark.parametrize("every", [0, 1])
def test_holding_out_every_view_is_refused(every):
    with pytest.raises(ValueError, match="nothing to train"):
        hold_out_indices(10, every, 0)
