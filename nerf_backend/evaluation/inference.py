"""Using a trained run: load its model and render a split's views into RUN/renders/SPLIT."""

from __future__ import annotations

import json
import time
from concurrent.futures import Executor
from pathlib import Path
from typing import Callable

import torch

from nerf_contract.run_layout import RENDERS_DIR

from ..configs.train_config import TrainConfig
from ..core.cpu_steal import StealMeter
from ..core.files import write_json
from ..core.progress import Progress
from ..data.dataset import DatasetSplit, load_cameras, load_scene_bounds, load_split
from ..data.run_folder import RunFolder
from ..model_components.ray_bounds import RayBounds, choose_ray_bounds
from ..models.base import Model
from ..models.registry import build_model
from .render_views import RenderedImage, render_poses

RENDERS_RECORD = "renders.json"


def load_trained_model(run: RunFolder, device: torch.device) -> tuple[Model, RayBounds, dict]:
    """The run's model with its latest checkpoint, its ray bounds, and the checkpoint's
    iteration and training time."""
    stored = run.read_config()
    config = TrainConfig.from_dict(stored["config"])
    state = run.load_checkpoint(device, mapped=True)  # the model's tensors copied into it, nothing else read
    ray_bounds, _ = choose_ray_bounds(config.ray_bounds, load_scene_bounds(stored["dataset"]))
    model = build_model(config, ray_bounds.box).to(device)
    model.restore(state["model"])
    model.eval()
    return model, ray_bounds, {"iteration": state["iteration"], "train_seconds": state["train_seconds"]}


def view_stem(image_path: Path) -> str:
    return image_path.stem


def render_split(run: RunFolder, split: str, device: torch.device, chunk: int | None = None,
                 progress: bool = True, scale: float = 1.0, dataset_split: DatasetSplit | None = None,
                 on_view: Callable[[int, RenderedImage], None] | None = None,
                 writer: Executor | None = None) -> Path:
    """Render every view of ``split`` with the run's latest checkpoint; returns the folder
    (``RUN/renders/SPLIT``, or ``RUN/renders/SPLIT_xSCALE`` at ``scale`` times the dataset's
    resolution, so the renders that ``eval`` scores keep their size). ``dataset_split``: the
    split, where the caller has read it already; ``on_view(index, image)``: called once each
    view's files are written, with what they hold; ``writer``: an executor that writes each view
    while the next renders (``render_poses``).

    The folder's ``renders.json`` records the checkpoint iteration, so stale renders (from
    before the run trained further) are recognised, and the seconds each view took."""
    stored = run.read_config()
    dataset_split = dataset_split if dataset_split is not None else load_split(stored["dataset"], split)
    model, ray_bounds, state = load_trained_model(run, device)
    intrinsics = dataset_split.intrinsics if scale == 1.0 else dataset_split.intrinsics.scaled(scale)
    out_dir = run.renders_dir(split) if scale == 1.0 else run.path / RENDERS_DIR / f"{split}_x{scale:g}"
    stems = [view_stem(p) for p in dataset_split.image_paths]
    bar = Progress(len(stems), f"render {split}", unit="view", enabled=progress)

    def view_done(index: int, image: RenderedImage) -> None:
        bar.update(1)
        if on_view is not None:
            on_view(index, image)

    start = time.perf_counter()
    with StealMeter() as steal:
        render_poses(model, intrinsics, dataset_split.poses, stems, ray_bounds, out_dir,
                     chunk=chunk, on_view=view_done, writer=writer)
    bar.close()
    write_json(out_dir / RENDERS_RECORD, {
        "split": split, "iteration": state["iteration"], "views": stems, "size": [intrinsics.width, intrinsics.height],
        "seconds_per_view": (time.perf_counter() - start) / len(stems), "device": str(device),
        # The share of the cores' time a hypervisor took meanwhile (None off Linux): on a shared
        # VM the seconds above may read slower than the machine is.
        "cpu_stolen_share": steal.share,
        "image": "RGB over white, 8-bit PNG", "depth": "STEM_depth.exr: Z = expected ray distance, A = opacity",
    })
    return out_dir


def render_cameras(run: RunFolder, cameras_json: Path, out_dir: Path, device: torch.device,
                   chunk: int | None = None) -> list[Path]:
    """Render the cameras of a transforms JSON (no images needed) into ``out_dir``."""
    cameras = load_cameras(cameras_json)
    model, ray_bounds, _ = load_trained_model(run, device)
    return render_poses(model, cameras.intrinsics, cameras.poses, cameras.stems, ray_bounds, out_dir, chunk=chunk)


def renders_are_current(run: RunFolder, split: str) -> bool:
    """True when RUN/renders/SPLIT was rendered from the run's latest checkpoint."""
    record = run.renders_dir(split) / RENDERS_RECORD
    if not record.exists() or not run.checkpoint_path.exists():
        return False
    rendered_iteration = json.loads(record.read_text()).get("iteration")
    return rendered_iteration == run.load_checkpoint(torch.device("cpu"), mapped=True)["iteration"]
