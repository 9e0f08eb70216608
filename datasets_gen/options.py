"""What a dataset generation run is asked to do, validated before Blender does any work.

Kept free of bpy so the CLI can reject bad input in a fraction of a second, and so the same
checks apply to the command line and to in-process callers (the add-on).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Optional

DEVICES = ("CPU", "GPU")
SPLITS = ("train", "val", "test")


class DatasetGenError(Exception):
    """A problem with the user's input or environment, reported as one line without a traceback."""


@dataclass(frozen=True)
class GeneratorOptions:
    """Settings of one run; defaults are the nerf_synthetic protocol's."""

    out_dir: str
    demo: bool = False
    blend_path: Optional[str] = None
    train_views: int = 100
    val_views: int = 100
    test_views: int = 200
    width: int = 800
    height: int = 800
    samples: int = 128
    seed: int = 0
    full_sphere: bool = False
    device: str = "CPU"
    overwrite: bool = False

    def views(self, split: str) -> int:
        """Number of views of a split."""
        return {"train": self.train_views, "val": self.val_views, "test": self.test_views}[split]

    @property
    def scene_source(self) -> str:
        """What the dataset was rendered from: "demo" or the absolute .blend path."""
        return "demo" if self.demo else os.path.abspath(str(self.blend_path))

    def validate(self) -> "GeneratorOptions":
        """Raise DatasetGenError naming the offending option; return self when all is well."""
        if self.demo == (self.blend_path is not None):
            raise DatasetGenError("give exactly one of SCENE.blend or --demo")
        if self.blend_path is not None:
            if not os.path.isfile(self.blend_path):
                raise DatasetGenError(f"scene file not found: {self.blend_path}")
            if not self.blend_path.lower().endswith(".blend"):
                raise DatasetGenError(f"scene file is not a .blend file: {self.blend_path}")
        _require(self.train_views >= 1, f"--train-views must be >= 1, got {self.train_views}")
        _require(self.val_views >= 0, f"--val-views must be >= 0, got {self.val_views}")
        _require(self.test_views >= 0, f"--test-views must be >= 0, got {self.test_views}")
        _require(
            1 <= self.width <= 16384 and 1 <= self.height <= 16384,
            f"resolution must be between 1 and 16384 pixels, got {self.width}x{self.height}",
        )
        _require(self.samples >= 1, f"--samples must be >= 1, got {self.samples}")
        _require(0 <= self.seed < 2**31, f"--seed must be in [0, 2^31), got {self.seed}")
        _require(self.device in DEVICES, f"--device must be one of {', '.join(DEVICES)}, got {self.device}")
        _require(bool(self.out_dir), "--out must name a folder")
        return self


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise DatasetGenError(message)
