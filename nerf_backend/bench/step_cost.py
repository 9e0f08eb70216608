"""``bench-step``: seconds per training iteration of a NeRF preset through this project's
trainer against a plain PyTorch implementation of the same maths."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from ..configs.presets import preset_config
from ..core.errors import NerfError
from ..core.files import write_json
from ..data.dataset import composite, load_split
from ..models.registry import build_model
from ..training.adam import Adam
from ..training.trainer import TrainOptions, train
from .plain_nerf import PlainNerf, plain_rays


def step_cost(dataset: Path, preset: str, steps: int, out_dir: Path, seed: int = 0, rays: int | None = None,
              overwrite: bool = False) -> dict:
    """Seconds per training iteration of a NeRF preset through this project's trainer,
    against ``plain_nerf.PlainNerf`` (the same maths written plainly) on the same data,
    rays per batch, threads and seed. Each side takes one untimed warm-up step."""
    config = preset_config(preset)
    if config.model != "nerf" or not config.field.view_dependent:
        raise NerfError(f"bench-step: {preset!r} is not a view-dependent NeRF preset; the plain yardstick is a NeRF MLP")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise NerfError(f"{out_dir}: bench folder exists and is not empty; pass --overwrite to replace it")
    out_dir.mkdir(parents=True, exist_ok=True)
    rays = rays or config.rays_per_batch
    overrides = (f"rays_per_batch={rays}", "checkpoint_every=1000000000")
    run_dir = out_dir / "runs" / preset
    common = dict(dataset=dataset, run=run_dir, seed=seed, progress=False, validate=False)
    warm = train(TrainOptions(**common, preset=preset, overrides=overrides, iterations=1, overwrite=True))
    timed = train(TrainOptions(**common, iterations=1 + steps, resume=True))
    ours = (timed.train_seconds - warm.train_seconds) / steps

    config = preset_config(preset)
    split = load_split(dataset, "train")
    torch.manual_seed(seed)
    plain = PlainNerf(config)
    optimizer = Adam([{"params": plain.parameters(), "lr": config.learning_rate}], betas=config.adam_betas,
                     eps=config.adam_eps)
    count, height, width = split.rgba.shape[:3]
    intrinsics = split.intrinsics
    seconds = []
    for step in range(1 + steps):
        start = time.perf_counter()
        image = torch.randint(count, (rays,))
        px, py = torch.randint(width, (rays,)), torch.randint(height, (rays,))
        rays_o, rays_d = plain_rays(intrinsics.fl_x, intrinsics.fl_y, intrinsics.cx, intrinsics.cy,
                                    split.poses[image], px.float(), py.float())
        loss = plain.loss(rays_o, rays_d, composite(split.rgba[image, py, px]))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step > 0:
            seconds.append(time.perf_counter() - start)
    plain_seconds = float(np.mean(seconds))
    ours_parameters = sum(p.numel() for p in build_model(config, None).parameters())
    plain_parameters = sum(p.numel() for p in plain.parameters())
    report = {
        "dataset": str(Path(dataset).resolve()), "preset": preset, "rays_per_batch": rays, "steps": steps,
        "seed": seed, "machine": {"torch": torch.__version__, "threads": torch.get_num_threads()},
        "seconds_per_iteration": {"project": ours, "plain": plain_seconds},
        "ratio_project_to_plain": ours / plain_seconds,
        "parameters": {"project": ours_parameters, "plain": plain_parameters},
        "comparison": ("this project's trainer (ray batch, coarse + fine render, loss, backward, Adam) against "
                       "nerf_backend/plain_nerf.py: the same MLPs, encodings, sample counts and optimiser written "
                       "plainly (one MLP call a pass, cumprod compositing, searchsorted resampling)"),
    }
    write_json(out_dir / "step_cost.json", report)
    return report
