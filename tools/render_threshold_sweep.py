"""What rendering's faint-cell threshold (``render_alpha_threshold``) costs and saves on a trained
run: every test view rendered at each threshold, with the mean and lowest PSNR, the fine march
steps a view and the seconds a view.

    python tools/render_threshold_sweep.py RUN [--thresholds 0,1e-3,1e-2] [--views N]

Threshold 0 renders every cell training keeps. The model and views are the same for each
threshold; only the grid rendering marches (``MarchedModel.render_occupancy``) changes.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nerf_backend.core.stage_timer import StageTimer  # noqa: E402
from nerf_backend.data.dataset import load_split  # noqa: E402
from nerf_backend.data.run_folder import RunFolder  # noqa: E402
from nerf_backend.evaluation.inference import load_trained_model  # noqa: E402
from nerf_backend.evaluation.render_views import render_image  # noqa: E402
from nerf_backend.metrics.image_metrics import psnr  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--thresholds", default="0,1e-3,1e-2")
    parser.add_argument("--views", type=int, default=None, help="every k-th test view so that about N are rendered")
    args = parser.parse_args()
    run = RunFolder(args.run)
    model, ray_bounds, _ = load_trained_model(run, torch.device("cpu"))
    split = load_split(run.read_config()["dataset"], "test")
    views = list(range(0, len(split), max(1, len(split) // args.views) if args.views else 1))
    print(f"{args.run}: {split.intrinsics.width}×{split.intrinsics.height}, {len(views)} test views, "
          f"{torch.get_num_threads()} threads")
    for alpha in (float(text) for text in args.thresholds.split(",")):
        model.render_density_threshold = -math.log1p(-alpha) / model.step
        scores, steps, seconds = [], 0, 0.0
        for view in views:
            with StageTimer(torch.device("cpu")) as timer:
                start = time.perf_counter()
                image = render_image(model, split.intrinsics, split.poses[view], ray_bounds)
                seconds += time.perf_counter() - start
            scores.append(psnr(image.rgb, split.rgb_on_white(view).numpy()))
            steps += int(timer.items["march"])
        print(f"  threshold {alpha:g}: {model.render_occupancy().occupied_fraction:.4f} of the cells kept, "
              f"PSNR mean {np.mean(scores):.3f} dB (lowest {min(scores):.3f}), {steps / len(views) / 1e6:.2f} M fine "
              f"steps and {seconds / len(views):.3f} s a view")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
