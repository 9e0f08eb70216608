"""The training loop: batches of random rays, coarse + fine photometric loss, Adam with
exponential learning-rate decay, validation as it goes, atomic checkpoints, resume and
cancel (SIGINT/SIGTERM finish the step, save, and stop)."""

from __future__ import annotations

import shutil
import signal
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from tqdm import tqdm

from .cameras import camera_rays, pixel_centres
from .config import TrainConfig, preset_config, with_overrides
from .auto import auto_config
from .dataset import DatasetSplit, SceneBounds, composite, load_scene_bounds, load_scene_profile, load_split
from .devices import autocast_dtype, resolve_device
from .errors import NerfError, RunError
from .files import write_png
from .metrics import mse_to_psnr
from .models import build_model, final_output
from .ray_bounds import RayBounds, choose_ray_bounds
from .render_views import render_image
from .run_folder import IN_USE, LOCK_NAME, RunFolder


@dataclass
class TrainOptions:
    dataset: Path
    run: Path
    preset: str | None = None  # None on resume: the run's own
    iterations: int | None = None  # total for the run; None: the preset's
    max_seconds: float | None = None  # total training seconds for the run
    seed: int = 0
    overrides: tuple[str, ...] = ()  # KEY=VALUE changes to the preset (new runs only)
    device: str = "auto"
    resume: bool = False
    overwrite: bool = False
    progress: bool = True
    validate: bool = True  # render validation views (False: timing runs that only train)


@dataclass
class TrainSummary:
    iteration: int
    train_seconds: float
    stop_reason: str  # "iterations", "time" or "cancelled"
    val_psnr: float | None


class _TrainingProgress:
    """A tqdm bar over iterations, or over training seconds when a time budget will end
    the run first (then the bar's time left is the real one)."""

    def __init__(self, iterations: int, iteration: int, max_seconds: float | None, seconds: float,
                 enabled: bool, description: str) -> None:
        self.by_time = max_seconds is not None
        total, initial = (max_seconds, seconds) if self.by_time else (iterations, iteration)
        self.bar = tqdm(total=total, initial=initial, disable=not enabled, desc=description, file=sys.stderr,
                        unit="s" if self.by_time else "it", dynamic_ncols=True,
                        bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
                        if self.by_time else None)
        self.iteration = iteration

    def step(self, iteration: int, seconds: float) -> None:
        if self.by_time:
            self.bar.update(min(seconds, self.bar.total) - self.bar.n)
        else:
            self.bar.update(iteration - self.iteration)
        self.iteration = iteration

    def show(self, **values: str) -> None:
        self.bar.set_postfix(it=self.iteration, **values) if self.by_time else self.bar.set_postfix(**values)

    def close(self) -> None:
        self.bar.close()


class _StopRequest:
    """Turns SIGINT/SIGTERM into a flag the loop checks between steps."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: dict[int, object] = {}

    def __enter__(self) -> "_StopRequest":
        import threading

        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        self.requested = True

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _existing_files(run: RunFolder) -> list[Path]:
    return [p for p in run.path.iterdir() if p.name != LOCK_NAME] if run.path.is_dir() else []


def _refuse_to_overwrite(run: RunFolder, options: TrainOptions, holding_lock: bool) -> None:
    """A non-empty folder is reused only when resuming or told to overwrite."""
    if not options.resume and not options.overwrite and _existing_files(run):
        if not holding_lock and run.in_use():  # the probe would see our own lock
            raise RunError(f"{run.path}: {IN_USE}")
        raise RunError(f"{run.path}: run folder exists and is not empty; pass --resume to continue it or --overwrite to replace it")


def _prepare_run_folder(run: RunFolder, options: TrainOptions) -> None:
    """Under the lock: check again, then empty the folder for a new run."""
    _refuse_to_overwrite(run, options, holding_lock=True)
    if options.resume:
        run.read_config()  # raises a clear error if this is not a run
        return
    for path in _existing_files(run):
        shutil.rmtree(path) if path.is_dir() else path.unlink()


def _load_val(dataset: Path) -> DatasetSplit | None:
    return load_split(dataset, "val") if (dataset / "transforms_val.json").exists() else None


def sample_ray_batch(
    split: DatasetSplit, batch: int, generator: torch.Generator, precrop_fraction: float | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random (image, pixel) indices: ``image [B]`` and row-major ``pixel [B]``, drawn from
    the central ``precrop_fraction`` of each image when given."""
    count, height, width = split.rgba.shape[:3]
    image = torch.randint(count, (batch,), generator=generator)
    if precrop_fraction is None:
        x = torch.randint(width, (batch,), generator=generator)
        y = torch.randint(height, (batch,), generator=generator)
    else:
        half_w = max(1, int(width * precrop_fraction / 2))
        half_h = max(1, int(height * precrop_fraction / 2))
        x = torch.randint(width // 2 - half_w, width // 2 + half_w, (batch,), generator=generator)
        y = torch.randint(height // 2 - half_h, height // 2 + half_h, (batch,), generator=generator)
    return image, y * width + x


def _optimizer(model: torch.nn.Module, config: TrainConfig) -> torch.optim.Optimizer:
    """Adam with the grids at ``learning_rate`` and MLPs at ``network_learning_rate`` (a
    NeRF has only MLPs, at ``learning_rate``). ``initial_lr`` is what decay scales."""
    grids = [p for name, p in model.named_parameters() if "_grid." in name]
    networks = [p for name, p in model.named_parameters() if "_grid." not in name]
    network_lr = config.network_learning_rate if grids else config.learning_rate
    groups = [{"params": grids, "initial_lr": config.learning_rate, "lr": config.learning_rate},
              {"params": networks, "initial_lr": network_lr, "lr": network_lr}]
    return torch.optim.Adam([g for g in groups if g["params"]], betas=config.adam_betas, eps=config.adam_eps)


def train(options: TrainOptions) -> TrainSummary:
    dataset = Path(options.dataset).resolve()
    # Read the whole dataset before touching the run folder: bad input leaves nothing behind.
    train_split = load_split(dataset, "train")
    val_split = _load_val(dataset) if options.validate else None
    scene_bounds = load_scene_bounds(dataset)
    run = RunFolder(options.run)
    _refuse_to_overwrite(run, options, holding_lock=False)  # before the lock: a refused folder gains no lock file
    run.acquire_lock()
    try:
        _prepare_run_folder(run, options)
        return _train_locked(run, dataset, train_split, val_split, scene_bounds, options)
    finally:
        run.release_lock()


def _train_locked(
    run: RunFolder, dataset: Path, train_split: DatasetSplit, val_split: DatasetSplit | None,
    scene_bounds: SceneBounds | None, options: TrainOptions,
) -> TrainSummary:
    device = resolve_device(options.device)
    if options.resume:
        stored = run.read_config()
        if options.preset is not None and options.preset != stored["preset"]:
            raise RunError(f"{run.path}: run was trained with preset {stored['preset']!r}, not {options.preset!r}")
        if Path(stored["dataset"]) != dataset:
            raise RunError(f"{run.path}: run was trained on {stored['dataset']}, not {dataset}")
        if options.overrides:
            raise RunError(f"{run.path}: --set applies to new runs; a resumed run keeps its config")
        config = TrainConfig.from_dict(stored["config"])
        seed = stored["seed"]
        max_seconds = options.max_seconds if options.max_seconds is not None else stored.get("max_seconds")
    else:
        config = with_overrides(preset_config(options.preset or "preview"), list(options.overrides))
        seed = options.seed
        max_seconds = options.max_seconds
    if options.iterations is not None:
        config = replace(config, iterations=options.iterations)

    if config.max_train_views is not None and config.max_train_views < len(train_split):
        train_split = train_split.subset(config.max_train_views)
    ray_bounds, bounds_reason = choose_ray_bounds(config.ray_bounds, scene_bounds)
    decisions = {"ray_bounds": {**ray_bounds.describe(), "reason": bounds_reason}}
    if config.preset == "auto" and not options.resume:
        config, auto_decisions = auto_config(config, train_split, ray_bounds.box, load_scene_profile(dataset))
        decisions.update(auto_decisions)
    elif options.resume:
        decisions = run.read_config().get("decisions", decisions)
    run.write_config({
        "dataset": str(dataset),
        "preset": config.preset,
        "seed": seed,
        "device": str(device),
        "max_seconds": max_seconds,
        "config": config.to_dict(),
        "decisions": decisions,
        "background": "white (RGBA composited as rgb·α + 1 − α)",
        "image_size": [train_split.intrinsics.width, train_split.intrinsics.height],
        "train_views": len(train_split),
    })

    amp_dtype = autocast_dtype(config.precision, device)
    # float16's narrow range needs the loss scaled so small gradients do not flush to zero.
    scaler = torch.amp.GradScaler(device.type, enabled=amp_dtype is torch.float16)
    torch.manual_seed(seed)
    model = build_model(config, ray_bounds.box).to(device)
    batch_generator = torch.Generator().manual_seed(seed)
    sample_generator = torch.Generator(device=device).manual_seed(seed + 1)
    iteration, train_seconds = 0, 0.0
    state = run.load_checkpoint(device) if options.resume and run.checkpoint_path.exists() else None
    if state is not None:
        model.match_state(state["model"])  # the grids' resolution at the checkpoint
        model.load_state_dict(state["model"])
    optimizer = _optimizer(model, config)  # built for the parameters as they now are
    if state is not None:
        optimizer.load_state_dict(state["optimizer"])
        if "grad_scaler" in state:
            scaler.load_state_dict(state["grad_scaler"])
        batch_generator.set_state(state["batch_rng"])
        sample_generator.set_state(state["sample_rng"].to(sample_generator.get_state().device))
        iteration, train_seconds = state["iteration"], state["train_seconds"]

    def checkpoint() -> None:
        # A non-finite weight never replaces the last good checkpoint.
        broken = [name for name, value in model.state_dict().items()
                  if value.is_floating_point() and not bool(torch.isfinite(value).all())]
        if broken:
            diverged(f"weights {', '.join(broken[:3])} are not finite")
        run.save_checkpoint({
            "iteration": iteration, "train_seconds": train_seconds, "model": model.state_dict(),
            "optimizer": optimizer.state_dict(), "batch_rng": batch_generator.get_state(),
            "sample_rng": sample_generator.get_state(), "config": config.to_dict(),
            **({"grad_scaler": scaler.state_dict()} if scaler.is_enabled() else {}),
        })
        run.log_event("checkpoint", iteration=iteration, elapsed_s=train_seconds, path=str(run.checkpoint_path))

    def diverged(what: str) -> None:
        kept = (f"the last good checkpoint is kept at {run.checkpoint_path}" if run.checkpoint_path.exists()
                else "no checkpoint had been written yet")
        message = (f"training diverged at iteration {iteration} ({what}); {kept}; "
                   f"try a lower learning_rate (--set learning_rate=...)")
        run.log_event("error", iteration=iteration, message=message)
        raise NerfError(message)

    rgba = train_split.rgba.to(device)
    poses = train_split.poses.to(device)
    height, width = rgba.shape[1:3]
    run.log_event("start", iteration=iteration, resumed=options.resume, preset=config.preset,
                  device=str(device), target_iterations=config.iterations, max_seconds=max_seconds)
    val_psnr: float | None = None
    stop_reason = "iterations"
    progress = _TrainingProgress(config.iterations, iteration, max_seconds, train_seconds,
                                 enabled=options.progress, description=f"train {config.preset}")
    model.train()
    with _StopRequest() as stop:
        while iteration < config.iterations:
            if max_seconds is not None and train_seconds >= max_seconds:
                stop_reason = "time"
                break
            if stop.requested:
                stop_reason = "cancelled"
                break
            step_start = time.perf_counter()
            precrop = config.precrop_fraction if iteration < config.precrop_iterations else None
            image_index, pixel_index = sample_ray_batch(train_split, config.rays_per_batch, batch_generator, precrop)
            image_index, pixel_index = image_index.to(device), pixel_index.to(device)
            pixels_rgba = rgba[image_index, pixel_index // width, pixel_index % width]
            if config.random_background:
                background = torch.rand((len(pixel_index), 3), generator=batch_generator).to(device)
            else:
                background = torch.ones((), device=device)
            target = composite(pixels_rgba, background)
            origins, directions = camera_rays(train_split.intrinsics, poses[image_index], pixel_centres(width, pixel_index))
            t_near, t_far = ray_bounds(origins, directions)
            decay = config.learning_rate_at(iteration) / config.learning_rate
            for group in optimizer.param_groups:
                group["lr"] = group["initial_lr"] * decay
            if model.before_step(iteration):
                optimizer = _optimizer(model, config)  # the grids were resampled
            with torch.autocast(device.type, dtype=amp_dtype or torch.float32, enabled=amp_dtype is not None):
                outputs = model(origins, directions, t_near, t_far, background=background,
                                generator=sample_generator)
            errors = [F.mse_loss(output.rgb.float(), target) for output in outputs]
            loss = torch.stack(errors).sum()
            final_mse = errors[-1]
            if not torch.isfinite(loss):
                diverged(f"loss {loss.item()}")
            optimizer.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()
            scaler.step(optimizer)
            scaler.update()
            iteration += 1
            train_seconds += time.perf_counter() - step_start
            progress.step(iteration, train_seconds)
            if iteration % config.log_every == 0 or iteration == config.iterations:
                batch_psnr = mse_to_psnr(final_mse.item())
                progress.show(loss=f"{loss.item():.4f}", psnr=f"{batch_psnr:.2f}")
                run.log_event("train", iteration=iteration, loss=loss.item(), psnr=batch_psnr,
                              lr=config.learning_rate_at(iteration), elapsed_s=train_seconds)
            if val_split is not None and iteration % config.validate_every == 0:
                val_psnr = _validate(model, val_split, ray_bounds, run, iteration, train_seconds)
            if iteration % config.checkpoint_every == 0:
                checkpoint()
    progress.close()
    if val_split is not None and (val_psnr is None or iteration % config.validate_every != 0):
        val_psnr = _validate(model, val_split, ray_bounds, run, iteration, train_seconds)
    checkpoint()
    run.log_event("done", iteration=iteration, elapsed_s=train_seconds, reason=stop_reason, val_psnr=val_psnr)
    return TrainSummary(iteration, train_seconds, stop_reason, val_psnr)


def _validate(
    model: torch.nn.Module, val_split: DatasetSplit, ray_bounds: RayBounds, run: RunFolder, iteration: int,
    train_seconds: float,
) -> float:
    """Render one validation view (cycling through them) and log its PSNR; the render
    becomes RUN/preview.png for anyone watching."""
    view = (iteration // max(1, model.config.validate_every)) % len(val_split)
    image = render_image(model, val_split.intrinsics, val_split.poses[view], ray_bounds)
    target = val_split.rgb_on_white(view).numpy()
    value = mse_to_psnr(float(((image.rgb - target) ** 2).mean()))
    write_png(run.path / "preview.png", image.rgb)
    run.log_event("val", iteration=iteration, psnr=value, view=view, elapsed_s=train_seconds)
    return value
