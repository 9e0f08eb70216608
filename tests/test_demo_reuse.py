"""The demo reuses its folder only when what is there is what it would render: a dataset from
an earlier demo with other settings (the demo moved from 100×100 to 400×400) is named and
rendered again, not silently trained on."""

from __future__ import annotations

import argparse
import json

from conftest import TINY_DEMO_ARGS
from nerf_backend.demo import _dataset_differences


def _args(**changes) -> argparse.Namespace:
    """The demo's arguments for the tiny demo dataset, with ``changes``."""
    flags = dict(zip(TINY_DEMO_ARGS[1::2], TINY_DEMO_ARGS[2::2]))
    values = {"resolution": int(flags["--resolution"]), "samples": int(flags["--samples"]),
              "seed": int(flags["--seed"]), "train_views": int(flags["--train-views"]),
              "val_views": int(flags["--val-views"]), "test_views": int(flags["--test-views"])}
    return argparse.Namespace(**{**values, **changes})


def test_the_same_settings_reuse_the_dataset(tiny_demo_dataset):
    assert _dataset_differences(tiny_demo_dataset, _args()) == []


def test_other_settings_are_each_named(tiny_demo_dataset):
    differences = _dataset_differences(tiny_demo_dataset, _args(resolution=400, samples=32, test_views=20))
    assert differences == ["size 40×40 instead of 400×400", "samples 16 instead of 32",
                           "views {'train': 30, 'val': 2, 'test': 4} instead of {'train': 30, 'val': 2, 'test': 20}"]


def test_a_dataset_that_does_not_record_its_settings_is_rendered_again(tmp_path):
    (tmp_path / "transforms_train.json").write_text(json.dumps({"frames": []}))
    assert _dataset_differences(tmp_path, _args()) == ["its transforms_train.json does not record them"]
