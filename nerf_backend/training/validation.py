"""Validation as training goes: one view rendered and scored against the blank image's PSNR
(the collapse guard's measure), the render kept as the run's preview."""

from __future__ import annotations

from dataclasses import dataclass

from nerf_contract import training_events as events
from nerf_contract.run_layout import PREVIEW_NAME

from ..core.files import write_png
from ..data.dataset import DatasetSplit
from ..data.run_folder import RunFolder
from ..evaluation.render_views import render_image
from ..metrics.image_metrics import psnr
from ..model_components.ray_bounds import RayBounds
from ..models.base import Model
from .collapse_guard import blank_psnr


@dataclass(frozen=True)
class ViewScore:
    """One validation: the model's PSNR on a view and the blank white image's on the same view."""

    iteration: int
    psnr: float
    blank_psnr: float


def validate_view(
    model: Model, val_split: DatasetSplit, ray_bounds: RayBounds, run: RunFolder, iteration: int,
    train_seconds: float, view: int,
) -> ViewScore:
    """Render validation view ``view`` and log its PSNR next to the blank image's; the render
    becomes RUN/preview.png for anyone watching."""
    image = render_image(model, val_split.intrinsics, val_split.poses[view], ray_bounds)
    target = val_split.rgb_on_white(view).numpy()
    score = ViewScore(iteration, psnr(image.rgb, target), blank_psnr(target))
    write_png(run.path / PREVIEW_NAME, image.rgb)
    run.log(events.Val(iteration=iteration, psnr=score.psnr, blank_psnr=score.blank_psnr, view=view,
                       elapsed_s=train_seconds))
    return score
