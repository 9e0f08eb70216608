"""Scoring renders against a dataset's ground truth: PSNR and SSIM per view and mean.

Both sides are 8-bit images (what is on disk) as float RGB in [0, 1]; the ground truth's
RGBA is composited over white, as the NeRF renders are."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image

from .dataset import DatasetSplit, composite
from .errors import NerfError
from .metrics import psnr, ssim


def read_rgb(path: Path) -> np.ndarray:
    """An image on disk as float RGB in [0, 1]; RGBA is composited over white."""
    if not path.is_file():
        raise NerfError(f"{path}: render not found")
    with Image.open(path) as image:
        rgba = torch.from_numpy(np.asarray(image.convert("RGBA")).copy())
    return composite(rgba).numpy()


def score_renders(split: DatasetSplit, renders_dir: Path) -> dict:
    """Metrics of ``renders_dir/STEM.png`` against each view of ``split``."""
    per_view = []
    for index, gt_path in enumerate(split.image_paths):
        render_path = renders_dir / f"{gt_path.stem}.png"
        rendered = read_rgb(render_path)
        reference = split.rgb_on_white(index).numpy()
        if rendered.shape != reference.shape:
            raise NerfError(f"{render_path}: size {rendered.shape[1]}×{rendered.shape[0]} differs from "
                            f"the ground truth's {reference.shape[1]}×{reference.shape[0]}")
        per_view.append({"view": gt_path.stem, "psnr": psnr(rendered, reference), "ssim": ssim(rendered, reference)})
    return {
        "split": split.name,
        "psnr": float(np.mean([v["psnr"] for v in per_view])),
        "ssim": float(np.mean([v["ssim"] for v in per_view])),
        "views": len(per_view),
        "background": "white: ground-truth RGBA composited as rgb·α + (1 − α)",
        "images": "8-bit PNGs on both sides, as float RGB in [0, 1]",
        "per_view": per_view,
    }
