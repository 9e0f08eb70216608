"""A trained run rendered along a camera animation: one PNG per frame and an H.264 video at the
scene's frame rate; with Cycles' frames beside the path, a side-by-side video
(Cycles | NeRF | error), PSNR and SSIM per frame in a JSON file, and their plot.

Layout (``OUT``, by default ``RUN/animation/CAMERA``)::

    OUT/frames/STEM.png           the NeRF's frames (RGB over white)
    OUT/nerf.mp4                  those frames as a video
    OUT/side_by_side/STEM.png     Cycles | NeRF | error heatmap        (with --cycles)
    OUT/side_by_side.mp4                                              (with --cycles)
    OUT/frame_metrics.json        PSNR, SSIM per frame and their means (with --cycles)
    OUT/frame_metrics.png         their plot                          (with --cycles)
    OUT/animation.json            what was rendered, from which checkpoint, and how fast

Resumable: frames already rendered from the same checkpoint and the same camera path are
kept, so an interrupted render continues where it stopped. Frames from an older checkpoint
or another path are rendered again (the record says which), as ``render`` does for a split.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from nerf_contract.run_layout import ANIMATION_FRAMES_DIR, ANIMATION_RECORD, ANIMATIONS_DIR

from ..core.errors import NerfError
from ..core.files import write_json, write_png
from ..core.plotting import pyplot
from ..core.progress import Progress
from ..core.video import write_video
from ..data.dataset import CameraAnimation, load_camera_animation
from ..data.run_folder import RunFolder
from ..metrics.registry import METRICS_BY_KEY, MetricTools, mean_scores, score_image
from .error_images import error_heatmap
from .evaluate import read_rgb
from .inference import load_trained_model
from .render_views import render_image

FRAME_METRICS = (METRICS_BY_KEY["psnr"], METRICS_BY_KEY["ssim"])  # LPIPS per 800×600 frame is too slow on a CPU


def default_out_dir(run: RunFolder, path_json: Path) -> Path:
    """``RUN/animation/NAME``: NAME is the camera path's folder (datasets_gen names it after the camera)."""
    return run.path / ANIMATIONS_DIR / Path(path_json).resolve().parent.name


def _path_digest(animation: CameraAnimation) -> str:
    """What decides the frames' pixels besides the checkpoint: every frame's pose and intrinsics."""
    parts = [(f.frame, f.intrinsics, [round(v, 6) for v in f.pose.flatten().tolist()]) for f in animation.frames]
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:16]


def _read_record(out_dir: Path) -> dict:
    try:
        return json.loads((out_dir / ANIMATION_RECORD).read_text())
    except (OSError, ValueError):
        return {}


def render_animation(run: RunFolder, path_json: Path, device: torch.device, out_dir: Path | None = None,
                     chunk: int | None = None, cycles: bool = False, progress: bool = True) -> dict:
    """Render the run along the camera path ``path_json``; return (and write) the record."""
    animation = load_camera_animation(path_json)
    if cycles:
        missing = [f.frame for f in animation.frames if f.cycles_path is None]
        if missing:
            raise NerfError(f"{path_json}: --cycles: frames {missing[:5]} have no Cycles render "
                            "(write the path with datasets_gen --camera-path CAMERA --with-cycles)")
        absent = [f.cycles_path for f in animation.frames if not f.cycles_path.is_file()]
        if absent:
            raise NerfError(f"{absent[0]}: Cycles frame not found ({len(absent)} missing); rerun datasets_gen "
                            "--camera-path CAMERA --with-cycles to render them")
    out_dir = Path(out_dir) if out_dir is not None else default_out_dir(run, path_json)
    frames_dir = out_dir / ANIMATION_FRAMES_DIR
    model, ray_bounds, state = load_trained_model(run, device)
    digest = _path_digest(animation)
    earlier = _read_record(out_dir)
    current = earlier.get("iteration") == state["iteration"] and earlier.get("path_digest") == digest
    todo = [f for f in animation.frames if not (current and (frames_dir / f"{f.stem}.png").is_file())]
    if not current and earlier:
        print(f"note: re-rendering {out_dir}: its frames came from iteration {earlier.get('iteration')} "
              f"or another camera path", flush=True)
    # The record names this checkpoint and path before the first frame, so the frames an
    # interrupted render leaves are recognised as current when it is resumed.
    record = {"camera": animation.camera, "camera_path": str(animation.path.resolve()), "fps": animation.fps,
              "frames": [f.frame for f in animation.frames], "size": list(animation.size),
              "iteration": state["iteration"], "path_digest": digest, "device": str(device),
              "seconds_per_frame": earlier.get("seconds_per_frame") if current else None}
    write_json(out_dir / ANIMATION_RECORD, record)
    bar = Progress(len(todo), f"render {animation.camera}", unit="frame", enabled=progress)
    started = time.perf_counter()
    for frame in todo:
        image = render_image(model, frame.intrinsics, frame.pose, ray_bounds, chunk)
        write_png(frames_dir / f"{frame.stem}.png", image.rgb)
        bar.update(1)
    bar.close()
    if todo:
        record["seconds_per_frame"] = (time.perf_counter() - started) / len(todo)
    stems = [f.stem for f in animation.frames]
    record["video"] = str(write_video(out_dir / "nerf.mp4", (read_rgb(frames_dir / f"{s}.png") for s in stems),
                                      animation.fps))
    if cycles:
        record.update(_compare_with_cycles(animation, frames_dir, out_dir))
    write_json(out_dir / ANIMATION_RECORD, record)
    return record


def _compare_with_cycles(animation: CameraAnimation, frames_dir: Path, out_dir: Path) -> dict:
    """Side-by-side frames and video, per-frame PSNR/SSIM (JSON and plot); the record's entries."""
    tools = MetricTools(lpips_unavailable="not computed per animation frame (too slow at video sizes on a CPU)")
    per_frame = []
    side_dir = out_dir / "side_by_side"

    def side_by_side():
        for frame in animation.frames:
            rendered, reference = read_rgb(frames_dir / f"{frame.stem}.png"), read_rgb(frame.cycles_path)
            if rendered.shape != reference.shape:
                raise NerfError(f"{frame.cycles_path}: {reference.shape[1]}×{reference.shape[0]}, but the path's "
                                f"frames are {rendered.shape[1]}×{rendered.shape[0]}")
            per_frame.append({"frame": frame.frame, **score_image(rendered, reference, tools, FRAME_METRICS)})
            joined = np.concatenate([reference, rendered, error_heatmap(rendered, reference)], axis=1)
            write_png(side_dir / f"{frame.stem}.png", joined)
            yield joined

    video = write_video(out_dir / "side_by_side.mp4", side_by_side(), animation.fps)
    means = mean_scores(per_frame, FRAME_METRICS)
    metrics = {"frames": per_frame, "mean": means, "reference": "Cycles, with the dataset's settings",
               "metrics": [metric.describe() for metric in FRAME_METRICS],
               "lpips_unavailable": tools.lpips_unavailable}
    write_json(out_dir / "frame_metrics.json", metrics)
    plot_frame_metrics(per_frame, out_dir / "frame_metrics.png", animation.camera)
    return {"side_by_side_video": str(video), "frame_metrics": str(out_dir / "frame_metrics.json"),
            "mean": means}


def plot_frame_metrics(per_frame: list[dict], path: Path, camera: str) -> None:
    """PSNR and SSIM against the frame number."""
    plt = pyplot()
    frames = [entry["frame"] for entry in per_frame]
    figure, axes = plt.subplots(1, len(FRAME_METRICS), figsize=(9, 3), dpi=100)
    for axis, metric in zip(axes, FRAME_METRICS):
        axis.plot(frames, [entry[metric.key] for entry in per_frame], marker="o", markersize=3, linewidth=1)
        axis.set_xlabel("frame")
        axis.set_ylabel(metric.label + (f" ({metric.unit})" if metric.unit else ""))
        axis.grid(alpha=0.3)
    figure.suptitle(f"NeRF against Cycles along {camera}", fontsize=10)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
