"""The collapse guard: a run whose validation images stay near the blank image has failed.

A NeRF that learns "nothing is there" renders the background everywhere: over white, the
blank white image. That image already scores a fair PSNR against a scene on a transparent
film (16-18 dB for an object filling most of the frame, more for a small one), so a
collapsed run can look like a weak one. The guard compares the model's validation PSNR with
the blank image's PSNR on the same views, computed from the validation images themselves:
within ``margin_db`` of it after ``collapse_check_after`` steps, the run has collapsed.

What the trainer does then (``recovery_config``): once, it starts the model again from a
new initialisation with a strategy that removes the usual causes, recorded with its reason
as ``auto``'s decisions are; if the restarted run collapses too, training stops and says so.

Example:
    >>> import numpy as np
    >>> round(blank_psnr(np.full((2, 2, 3), 0.9, np.float32)), 2)  # white against a 0.9 grey
    20.0
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch

from ..configs.train_config import TrainConfig
from ..data.dataset import DatasetSplit
from ..evaluation.render_views import render_image
from ..metrics.image_metrics import psnr
from ..model_components.ray_bounds import RayBounds

# At most this many views decide a verdict: enough that one odd view cannot, few enough to
# be cheap next to training (a fast 100×100 view renders in about 0.1 s on 2 cores).
GUARD_VIEWS = 4


def blank_psnr(image_on_white: np.ndarray) -> float:
    """PSNR of the blank white image (what an empty model renders) against ``image_on_white``."""
    return psnr(np.ones_like(image_on_white), image_on_white)


def guard_views(split: DatasetSplit) -> list[int]:
    """Up to ``GUARD_VIEWS`` evenly spaced views with something in them (a view that is
    all background scores the blank image perfectly and tells nothing)."""
    showing = [i for i in range(len(split)) if math.isfinite(blank_psnr(split.rgb_on_white(i).numpy()))]
    if len(showing) <= GUARD_VIEWS:
        return showing
    return [showing[round(k * (len(showing) - 1) / (GUARD_VIEWS - 1))] for k in range(GUARD_VIEWS)]


@dataclass(frozen=True)
class Verdict:
    """The guard's measurement at one iteration: mean PSNRs over the same views."""

    iteration: int
    psnr: float
    blank_psnr: float
    margin_db: float
    views: tuple[int, ...]

    @property
    def collapsed(self) -> bool:
        return self.psnr < self.blank_psnr + self.margin_db

    def describe(self) -> str:
        return (f"validation PSNR {self.psnr:.2f} dB at iteration {self.iteration} is within "
                f"{self.margin_db:g} dB of the blank white image's {self.blank_psnr:.2f} dB")


def judge(model: torch.nn.Module, split: DatasetSplit, views: list[int], ray_bounds: RayBounds, iteration: int,
          margin_db: float) -> Verdict:
    """Render ``views`` of ``split`` and compare them with the blank image on the same views."""
    model_psnrs, blank_psnrs = [], []
    for view in views:
        target = split.rgb_on_white(view).numpy()
        image = render_image(model, split.intrinsics, split.poses[view], ray_bounds)
        model_psnrs.append(psnr(image.rgb, target))
        blank_psnrs.append(blank_psnr(target))
    return Verdict(iteration, float(np.mean(model_psnrs)), float(np.mean(blank_psnrs)), margin_db, tuple(views))


class CollapseGuard:
    """Watches a run's validations. Each validation renders one view; only when that view is
    within the margin of its blank image does the guard render its views to decide (so a
    healthy run pays nothing)."""

    def __init__(self, split: DatasetSplit | None, ray_bounds: RayBounds, margin_db: float) -> None:
        self.split = split
        self.views = guard_views(split) if split is not None else []
        self.ray_bounds = ray_bounds
        self.margin_db = margin_db

    def confirm(self, model: torch.nn.Module, view_psnr: float, view_blank_psnr: float, iteration: int) -> Verdict | None:
        """The verdict when the run has collapsed, else None."""
        suspicious = math.isfinite(view_blank_psnr) and view_psnr < view_blank_psnr + self.margin_db
        if not suspicious or not self.views or self.split is None:
            return None
        verdict = judge(model, self.split, self.views, self.ray_bounds, iteration, self.margin_db)
        return verdict if verdict.collapsed else None


def recovery_config(config: TrainConfig, has_transparency: bool) -> tuple[TrainConfig, dict[str, object], list[str]]:
    """The config a collapsed run starts again with, the settings changed, and why each.

    Each change removes one known cause of an empty model: over a random background colour
    "nothing is there" stops being a minimum (when the images have alpha to tell background
    from scene); a halved learning rate keeps the first large steps from pushing density to
    zero across the scene; the paper's centre crop makes the first steps see the object."""
    changes: dict[str, object] = {"learning_rate": config.learning_rate / 2,
                                  "network_learning_rate": config.network_learning_rate / 2}
    reasons = ["a new initialisation (another seed)",
               "half the learning rate, so the first large steps cannot push density to zero across the scene"]
    if has_transparency and not config.random_background:
        changes["random_background"] = True
        reasons.append("random background colours: the alpha decides what is background, so an empty "
                       "scene stops being a minimum")
    if config.model == "nerf" and config.precrop_iterations < config.collapse_check_after:
        changes["precrop_iterations"] = config.collapse_check_after
        reasons.append(f"centre crops for the first {config.collapse_check_after} steps, so early rays hit the object")
    return dataclasses.replace(config, **changes), changes, reasons  # type: ignore[arg-type]
