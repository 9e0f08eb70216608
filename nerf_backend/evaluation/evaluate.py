"""Scoring renders against a dataset's ground truth: PSNR, SSIM, LPIPS and depth error, per
view and mean.

Colour: both sides are 8-bit images (what is on disk) as float RGB in [0, 1]; the ground
truth's RGBA is composited over white, as the NeRF renders are. Depth: where the dataset has
ground-truth depth (``depth_file_path``, distance along the ray, alpha in ``A``) and the renders
folder has ``STEM_depth.exr`` (this project's renders: expected distance ``Z`` and opacity
``A``), the mean absolute error on pixels that are foreground in both (alpha > 0.5), with the
rendered distance divided by its opacity so that a half-transparent pixel is not counted
as nearer than it is.

The renders may come from any tool: ``STEM.png`` per ground-truth view is all that is needed.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from nerf_contract.run_layout import COMPARE_NAME, DIFFERENCE_NAME, METRICS_NAME, SIDE_BY_SIDE_NAME

from ..core.errors import NerfError
from ..core.files import eight_bit, read_exr, write_json, write_png
from ..data.dataset import DatasetSplit, composite, load_split
from ..data.run_folder import RunFolder
from ..metrics.image_metrics import SSIM_SIGMA, SSIM_WINDOW
from ..metrics.lpips_metric import LpipsUnavailable, load_lpips
from ..metrics.registry import METRICS, MetricTools, mean_scores, score_image, summary_line, unavailable_reasons
from .error_images import ERROR_SCALE, error_heatmap
from .inference import render_split, renders_are_current
from .render_views import RenderedImage

FOREGROUND_ALPHA = 0.5
DEPTH_MASK = f"pixels whose ground-truth alpha and rendered opacity both exceed {FOREGROUND_ALPHA}"


def unit_float(pixels: np.ndarray) -> np.ndarray:
    """8-bit RGB as float32 in [0, 1]: a PNG read back, or the pixels it was written from."""
    return pixels.astype(np.float32) / np.float32(255.0)


def read_rgb(path: Path) -> np.ndarray:
    """An image on disk as float RGB in [0, 1]; RGBA is composited over white."""
    if not path.is_file():
        raise NerfError(f"{path}: render not found")
    try:
        with Image.open(path) as image:
            if image.mode == "RGB":  # no alpha (this project's renders): nothing to composite, the same floats
                return unit_float(np.asarray(image))
            rgba = torch.from_numpy(np.asarray(image.convert("RGBA")).copy())
    except OSError as exc:
        raise NerfError(f"{path}: cannot read image ({exc})") from None
    return composite(rgba).numpy()


def depth_error(truth_path: Path, render_path: Path,
                rendered: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float | None, int]:
    """Mean absolute depth error over the pixels foreground in both, and their count.
    ``rendered``: the render's distance and opacity where the caller holds them (what
    ``render_path`` stores), so the file is not read back."""
    truth = read_exr(truth_path)
    render = read_exr(render_path) if rendered is None else {"Z": rendered[0], "A": rendered[1]}
    for path, channels in ((truth_path, truth), (render_path, render)):
        if not {"Z", "A"} <= set(channels):
            raise NerfError(f"{path}: depth EXR needs channels Z and A, has {sorted(channels)}")
    if truth["Z"].shape != render["Z"].shape:
        raise NerfError(f"{render_path}: depth size {render['Z'].shape} differs from the ground truth's {truth['Z'].shape}")
    mask = (truth["A"] > FOREGROUND_ALPHA) & (render["A"] > FOREGROUND_ALPHA)
    count = int(mask.sum())
    if count == 0:
        return None, 0
    rendered_distance = render["Z"][mask] / render["A"][mask]
    return float(np.abs(rendered_distance - truth["Z"][mask]).mean()), count


def score_view(split: DatasetSplit, renders_dir: Path, tools: MetricTools, index: int,
               image: RenderedImage | None = None) -> tuple[dict, str | None]:
    """Every metric of the registry for view ``index``'s render ``renders_dir/STEM.png``, and
    why its depth was not scored (None where it was). ``image``: the render those files were
    written from, where the caller holds it: its 8-bit pixels and its depth are then scored
    as written, without reading them back (20-40 ms an 800×800 view)."""
    gt_path = split.image_paths[index]
    render_path = renders_dir / f"{gt_path.stem}.png"
    rendered = read_rgb(render_path) if image is None else unit_float(eight_bit(image.rgb))
    reference = split.rgb_on_white(index).numpy()
    if rendered.shape != reference.shape:
        raise NerfError(f"{render_path}: size {rendered.shape[1]}×{rendered.shape[0]} differs from "
                        f"the ground truth's {reference.shape[1]}×{reference.shape[0]}")
    view = {"view": gt_path.stem, **score_image(rendered, reference, tools), "depth_mae": None, "depth_pixels": 0}
    truth_depth, render_depth = split.depth_path(index), renders_dir / f"{gt_path.stem}_depth.exr"
    if truth_depth is None:
        return view, "the dataset has no ground-truth depth (no 'depth_file_path' in its frames)"
    if not truth_depth.is_file():
        return view, f"{truth_depth}: ground-truth depth file not found"
    if image is None and not render_depth.is_file():
        return view, f"the renders have no depth ({render_depth.name} not found)"
    held = None if image is None else (image.depth, image.opacity)
    view["depth_mae"], view["depth_pixels"] = depth_error(truth_depth, render_depth, held)
    return view, None


def _scorer() -> ThreadPoolExecutor:
    # Views scored side by side: decoding PNGs and the compiled SSIM (a ctypes call) leave the GIL.
    return ThreadPoolExecutor(max_workers=max(1, torch.get_num_threads()))


def score_renders(split: DatasetSplit, renders_dir: Path, tools: MetricTools,
                  scored: list[tuple[dict, str | None]] | None = None) -> dict:
    """Every metric of the registry for ``renders_dir/STEM.png`` against each view of
    ``split``, per view and as means; a metric the ``tools`` cannot compute (LPIPS without
    its weights) is None with the reason beside it. ``scored``: ``score_view``'s results for
    every view, where the caller has them already."""
    if scored is None:
        with _scorer() as pool:
            scored = list(pool.map(lambda index: score_view(split, renders_dir, tools, index),
                                   range(len(split.image_paths))))
    per_view = [view for view, _ in scored]
    depth_reason = next((reason for _, reason in reversed(scored) if reason is not None), None)
    depth_values = [v["depth_mae"] for v in per_view if v["depth_mae"] is not None]
    depth_mean = float(np.mean(depth_values)) if depth_values else None
    return {
        "split": split.name,
        "views": len(per_view),
        **mean_scores(per_view),
        "metrics": [metric.describe() for metric in METRICS],
        "lpips_net": "AlexNet, LPIPS v0.1",
        "lpips_unavailable": None,  # always present (readers look for it); the reason when LPIPS is missing:
        **unavailable_reasons(tools),
        "depth_mae": depth_mean,
        "depth_mask": DEPTH_MASK,
        "depth_unavailable": None if depth_mean is not None else (depth_reason or "no foreground pixels in common"),
        "background": "white: ground-truth RGBA composited as rgb·α + (1 − α); renders as written",
        "images": "8-bit PNGs on both sides, as float RGB in [0, 1]",
        "ssim_settings": (f"{SSIM_WINDOW}×{SSIM_WINDOW} Gaussian window, σ = {SSIM_SIGMA}, RGB in [0, 1] "
                          "(scikit-image's structural_similarity)"),
        "per_view": per_view,
    }




def metric_tools(weights: Path | None, linear: Path | None, device: torch.device) -> MetricTools:
    """What the metrics need: the LPIPS network, or the reason it is unavailable (never a
    made-up number)."""
    try:
        return MetricTools(lpips=load_lpips(weights, linear, device))
    except LpipsUnavailable as exc:
        return MetricTools(lpips_unavailable=str(exc))


def evaluate_run(run_path: Path, split: str, device: torch.device, lpips_weights: Path | None = None,
                 lpips_linear: Path | None = None, chunk: int | None = None, progress: bool = True) -> dict:
    """Render ``split`` with the run's latest checkpoint if its renders are stale, score
    them, and write ``RUN/metrics.json``."""
    run = RunFolder(run_path)
    stored = run.read_config()
    dataset_split = load_split(stored["dataset"], split)
    tools = metric_tools(lpips_weights, lpips_linear, device)
    scored = None
    if not renders_are_current(run, split):
        # Each view is written, then scored, beside the next view's render (written in the main
        # thread, its PNG and EXR took 0.7 s of lego's 13 views with nothing else running).
        with _scorer() as pool:
            pending: list[Future] = []
            render_split(run, split, device, chunk=chunk, progress=progress, dataset_split=dataset_split,
                         writer=pool, on_view=lambda index, image: pending.append(
                             pool.submit(score_view, dataset_split, run.renders_dir(split), tools, index, image)))
            scored = [done.result() for done in pending]
    metrics = score_renders(dataset_split, run.renders_dir(split), tools, scored)
    metrics.update(dataset=stored["dataset"], renders=str(run.renders_dir(split).resolve()))
    write_json(run.path / METRICS_NAME, metrics)
    return metrics


def evaluate_renders(dataset: Path, renders: Path, split: str, device: torch.device, out_dir: Path | None = None,
                     lpips_weights: Path | None = None, lpips_linear: Path | None = None) -> dict:
    """Score a folder of renders made by any tool (``STEM.png`` per view of ``split``) and
    write ``metrics.json`` into ``out_dir`` (default: the renders folder)."""
    if not renders.is_dir():
        raise NerfError(f"{renders}: renders folder not found")
    tools = metric_tools(lpips_weights, lpips_linear, device)
    metrics = score_renders(load_split(dataset, split), renders, tools)
    metrics.update(dataset=str(Path(dataset).resolve()), renders=str(renders.resolve()))
    out_dir = out_dir or renders
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / METRICS_NAME, metrics)
    return metrics


def compare_images(reference: Path, render: Path, out_dir: Path, device: torch.device,
                   lpips_weights: Path | None = None, lpips_linear: Path | None = None) -> dict:
    """One render against one reference image (e.g. Cycles and the NeRF from the same
    camera): PSNR, SSIM, LPIPS (or why not), and ``difference.png``, the error heatmap on the
    report's scale. Written to ``out_dir/compare.json``."""
    a, b = read_rgb(render), read_rgb(reference)
    if a.shape != b.shape:
        raise NerfError(f"{render}: size {a.shape[1]}×{a.shape[0]} differs from {reference}'s {b.shape[1]}×{b.shape[0]}")
    tools = metric_tools(lpips_weights, lpips_linear, device)
    scores = score_image(a, b, tools)
    result = {
        "reference": str(reference), "render": str(render), **scores,
        # Each metric with its value as shown (the add-on draws these rows as they are).
        "metrics": [{**metric.describe(), "value": scores[metric.key], "text": metric.format(scores[metric.key])}
                    for metric in METRICS],
        "lpips_unavailable": None, **unavailable_reasons(tools),
        "difference": str(out_dir / DIFFERENCE_NAME),
        "difference_scale": f"mean |render - reference| per pixel, 0 to {ERROR_SCALE} (inferno)",
        "side_by_side": str(out_dir / SIDE_BY_SIDE_NAME),
    }
    heatmap = error_heatmap(a, b)
    write_png(out_dir / DIFFERENCE_NAME, heatmap)
    caption = summary_line(result, separator="   ")
    write_png(out_dir / SIDE_BY_SIDE_NAME, side_by_side(
        [(b, "Cycles (reference)"), (a, "NeRF"), (heatmap, f"|difference|, 0 to {ERROR_SCALE}")], caption))
    write_json(out_dir / COMPARE_NAME, result)
    return result


def side_by_side(images: list[tuple[np.ndarray, str]], caption: str, min_tile: int = 256) -> np.ndarray:
    """Images (H×W×3 floats in [0, 1], one size) in a row, each titled, over a caption line:
    what the add-on shows in Blender's Image Editor after a comparison. Small images are
    enlarged by whole pixels (no smoothing hides the NeRF's errors)."""
    height, width = images[0][0].shape[:2]
    scale = max(1, -(-min_tile // max(height, width)))
    text_height, gap = 22, 4
    canvas = Image.new("RGB", (len(images) * (width * scale + gap) - gap, height * scale + 2 * text_height), "white")
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default(size=14)
    for index, (pixels, title) in enumerate(images):
        tile = Image.fromarray(np.clip(np.round(pixels[..., :3] * 255.0), 0, 255).astype(np.uint8))
        x = index * (width * scale + gap)
        canvas.paste(tile.resize((width * scale, height * scale), Image.Resampling.NEAREST), (x, text_height))
        draw.text((x + 4, 3), title, fill="black", font=font)
    draw.text((4, height * scale + text_height + 3), caption, fill="black", font=font)
    return np.asarray(canvas, dtype=np.float32) / 255.0
