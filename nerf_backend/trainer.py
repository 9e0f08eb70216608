"""The training loop: batches of random rays, coarse + fine photometric loss, Adam with
exponential learning-rate decay, validation as it goes, atomic checkpoints, resume and
cancel (SIGINT/SIGTERM finish the step, save, and stop)."""

from __future__ import annotations

import shutil
import signal
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F

from .cameras import camera_rays, pixel_centres
from .config import TrainConfig, preset_config, with_overrides
from .auto import auto_config
from .dataset import DatasetSplit, composite, load_scene_bounds, load_scene_profile, load_split
from .devices import autocast_dtype, resolve_device
from .errors import NerfError, RunError
from .files import write_png
from .collapse_guard import CollapseGuard, Verdict, blank_psnr, recovery_config
from .metrics import mse_to_psnr, psnr
from .models import build_model
from .occupancy_prior import PRIOR_KINDS, OccupancyPrior, load_occupancy_prior
from .progress import Progress
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
    stop_reason: str  # "iterations", "time", "cancelled" or "collapsed"
    val_psnr: float | None
    collapse: Verdict | None = None  # the guard's last verdict when the run ended collapsed
    started_at: int = 0  # the iteration this call began at (a resumed run's checkpoint)

    @property
    def had_nothing_to_do(self) -> bool:
        """A resumed run that was already at its iteration count or time budget."""
        return self.started_at == self.iteration and self.stop_reason in ("iterations", "time")


class _TrainingProgress:
    """Progress over iterations, or over training seconds when a time budget will end the run
    first (then the time left is the real one)."""

    def __init__(self, iterations: int, iteration: int, max_seconds: float | None, seconds: float,
                 enabled: bool, description: str) -> None:
        self.by_time = max_seconds is not None
        total, initial = (max_seconds, seconds) if self.by_time else (iterations, iteration)
        self.bar = Progress(total, description, unit="s" if self.by_time else "it", initial=initial,
                            enabled=enabled, seconds=self.by_time)
        self.iteration = iteration

    def step(self, iteration: int, seconds: float) -> None:
        self.bar.advance_to(seconds if self.by_time else iteration)
        self.iteration = iteration

    def show(self, **values: str) -> None:
        self.bar.set_postfix(it=self.iteration, **values) if self.by_time else self.bar.set_postfix(**values)

    def note(self, message: str) -> None:
        """A line above the bar (or alone on stderr when the bar is off): events the user must see."""
        self.bar.write(message)

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
    # Read the whole dataset and settle the run before touching its folder: bad input
    # (a broken dataset, a bad --set, a missing prior) leaves nothing behind.
    train_split = load_split(dataset, "train")
    val_split = _load_val(dataset) if options.validate else None
    run = RunFolder(options.run)
    _refuse_to_overwrite(run, options, holding_lock=False)  # before the lock: a refused folder gains no lock file
    plan = _plan_run(run, dataset, train_split, options)
    run.acquire_lock()
    try:
        _prepare_run_folder(run, options)
        return _train_locked(run, plan, val_split, options)
    finally:
        run.release_lock()


@dataclass
class _RunPlan:
    """What a run trains with: its settings, the decisions behind them and what it reads."""

    dataset: Path
    config: TrainConfig
    seed: int
    max_seconds: float | None
    device: torch.device
    train_split: DatasetSplit
    ray_bounds: RayBounds
    prior: OccupancyPrior | None
    decisions: dict

    def record(self) -> dict:
        """The run's config.json."""
        return {
            "dataset": str(self.dataset),
            "preset": self.config.preset,
            "seed": self.seed,
            "device": str(self.device),
            "max_seconds": self.max_seconds,
            "config": self.config.to_dict(),
            "decisions": self.decisions,
            "background": "white (RGBA composited as rgb·α + 1 − α)",
            "image_size": [self.train_split.intrinsics.width, self.train_split.intrinsics.height],
            "train_views": len(self.train_split),
        }


def _plan_run(run: RunFolder, dataset: Path, train_split: DatasetSplit, options: TrainOptions) -> _RunPlan:
    """A new run's settings from its preset, ``--set`` and (``auto``) the scene; a resumed
    run's from its folder. Reads only."""
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
    ray_bounds, bounds_reason = choose_ray_bounds(config.ray_bounds, load_scene_bounds(dataset))
    decisions = {"ray_bounds": {**ray_bounds.describe(), "reason": bounds_reason}}
    if options.resume:
        decisions = stored.get("decisions", decisions)
    elif config.preset == "auto":
        user_set = frozenset(assignment.partition("=")[0] for assignment in options.overrides)
        config, auto_decisions = auto_config(config, train_split, ray_bounds.box, load_scene_profile(dataset), user_set)
        decisions.update(auto_decisions)
    return _RunPlan(dataset, config, seed, max_seconds, device, train_split, ray_bounds,
                    _occupancy_prior(dataset, config), decisions)


def _train_locked(run: RunFolder, plan: _RunPlan, val_split: DatasetSplit | None, options: TrainOptions) -> TrainSummary:
    config, seed, max_seconds, device = plan.config, plan.seed, plan.max_seconds, plan.device
    train_split, ray_bounds, prior, decisions = plan.train_split, plan.ray_bounds, plan.prior, plan.decisions
    # The checkpoint first: a resume it refuses (damaged, or holding code) leaves the run as it was.
    state = run.load_checkpoint(device) if options.resume and run.checkpoint_path.exists() else None
    record = plan.record()
    run.write_config(record)

    amp_dtype = autocast_dtype(config.precision, device)
    # float16's narrow range needs the loss scaled so small gradients do not flush to zero.
    scaler = torch.amp.GradScaler(device.type, enabled=amp_dtype is torch.float16)
    # A run that collapsed starts again at `start_iteration` (its schedules count from
    # there); `attempt` counts those starts.
    restart = {"attempt": 0, "start_iteration": 0}
    model = _new_model(config, ray_bounds, prior, seed, restart["attempt"], device)
    batch_generator = torch.Generator().manual_seed(seed)
    sample_generator = torch.Generator(device=device).manual_seed(seed + 1)
    iteration, train_seconds = 0, 0.0
    if state is not None:
        restart = state.get("restart", restart)
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
    started_at = iteration

    def checkpoint() -> None:
        # A non-finite weight never replaces the last good checkpoint.
        broken = [name for name, value in model.state_dict().items()
                  if value.is_floating_point() and not bool(torch.isfinite(value).all())]
        if broken:
            diverged(f"weights {', '.join(broken[:3])} are not finite")
        run.save_checkpoint({
            "iteration": iteration, "train_seconds": train_seconds, "model": model.state_dict(),
            "optimizer": optimizer.state_dict(), "batch_rng": batch_generator.get_state(),
            "sample_rng": sample_generator.get_state(), "config": config.to_dict(), "restart": restart,
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
                  device=str(device), cpu_threads=torch.get_num_threads(), target_iterations=config.iterations,
                  max_seconds=max_seconds)
    val_psnr: float | None = None
    score: _ViewScore | None = None
    collapse: Verdict | None = None
    stop_reason = "iterations"
    progress = _TrainingProgress(config.iterations, iteration, max_seconds, train_seconds,
                                 enabled=options.progress, description=f"train {config.preset}")
    guard = CollapseGuard(val_split, ray_bounds, config.collapse_margin_db)

    def report_collapse(verdict: Verdict, action: str, final: bool) -> None:
        run.log_event("collapse", iteration=verdict.iteration, elapsed_s=train_seconds, val_psnr=verdict.psnr,
                      blank_psnr=verdict.blank_psnr,
                      margin_db=verdict.margin_db, views=list(verdict.views), action=action,
                      reason=verdict.describe(), final=final)
        progress.note(f"collapse: {verdict.describe()}; {action}")

    def collapsed_run_restarts() -> bool:
        """After a collapse: start again once with the recovery config (True), else stop."""
        nonlocal config, model, optimizer
        if restart["attempt"] >= 1:
            report_collapse(collapse, "stopped: it had already been restarted once", final=True)
            return False
        config, changes, reasons = recovery_config(config, has_transparency=bool((rgba[..., 3] < 255).any()))
        action = "restarted from a new start with " + "; ".join(reasons)
        decisions["collapse_recovery"] = {"value": changes, "at_iteration": iteration,
                                          "reason": f"{collapse.describe()}: {action}"}
        restart.update(attempt=restart["attempt"] + 1, start_iteration=iteration)
        run.write_config({**record, "config": config.to_dict(), "decisions": decisions})
        model = _new_model(config, ray_bounds, prior, seed, restart["attempt"], device)
        optimizer = _optimizer(model, config)
        report_collapse(collapse, action, final=False)
        return True

    model.train()
    with _StopRequest() as stop:
        while iteration < config.iterations:
            if max_seconds is not None and train_seconds >= max_seconds:
                stop_reason = "time"
                break
            if stop.requested:
                stop_reason = "cancelled"
                break
            step = iteration - restart["start_iteration"]  # the schedules' step
            step_start = time.perf_counter()
            precrop = config.precrop_fraction if step < config.precrop_iterations else None
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
            decay = config.learning_rate_decay(step)
            for group in optimizer.param_groups:
                group["lr"] = group["initial_lr"] * decay
            if model.before_step(step):
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
                              lr=config.learning_rate_at(step + 1), elapsed_s=train_seconds)
            if val_split is not None and iteration % config.validate_every == 0:
                score = _validate(model, val_split, ray_bounds, run, iteration, train_seconds)
                val_psnr = score.psnr
                if iteration - restart["start_iteration"] >= config.collapse_check_after:
                    collapse = guard.confirm(model, score.psnr, score.blank_psnr, iteration)
                    if collapse is not None and not collapsed_run_restarts():
                        stop_reason = "collapsed"
                        break
            if iteration % config.checkpoint_every == 0:
                checkpoint()
    progress.close()
    if val_split is not None and stop_reason != "collapsed":
        if score is None or score.iteration != iteration:
            score = _validate(model, val_split, ray_bounds, run, iteration, train_seconds)
            val_psnr = score.psnr
        # A run old enough to judge never ends silently on a near-blank model; nor does one
        # restarted after a collapse, however young (a young first start is not yet called a
        # failure: it may simply not have started).
        judged = (iteration - restart["start_iteration"] >= config.collapse_check_after or restart["attempt"] >= 1)
        collapse = guard.confirm(model, score.psnr, score.blank_psnr, iteration) if judged else None
        if collapse is not None:
            report_collapse(collapse, f"none: the run ended ({stop_reason}) before it could recover", final=True)
            stop_reason = "collapsed"
    checkpoint()
    run.log_event("done", iteration=iteration, elapsed_s=train_seconds, reason=stop_reason, val_psnr=val_psnr)
    return TrainSummary(iteration, train_seconds, stop_reason, val_psnr, collapse=collapse, started_at=started_at)


def _occupancy_prior(dataset: Path, config: TrainConfig) -> OccupancyPrior | None:
    """The dataset's occupancy prior of the kind ``config`` asks for (grid models only)."""
    if config.model != "grid" or config.occupancy_prior == "none":
        return None
    if config.occupancy_prior not in PRIOR_KINDS:
        raise NerfError(f"occupancy_prior {config.occupancy_prior!r}: choose none, {', '.join(PRIOR_KINDS)}")
    prior = load_occupancy_prior(dataset, config.occupancy_prior)
    if prior is None:
        raise NerfError(f"{dataset}: occupancy_prior={config.occupancy_prior} asked for, but the dataset has no "
                        f"occupancy prior (scene_profile.json names none); use occupancy_prior=none")
    return prior


def _new_model(config: TrainConfig, ray_bounds: RayBounds, prior: OccupancyPrior | None, seed: int, attempt: int,
               device: torch.device) -> torch.nn.Module:
    """A freshly initialised model; each restart after a collapse draws another initialisation."""
    torch.manual_seed(seed + 1000 * attempt)
    return build_model(config, ray_bounds.box, prior).to(device)


@dataclass(frozen=True)
class _ViewScore:
    """One validation: the model's PSNR on a view and the blank white image's on the same view."""

    iteration: int
    psnr: float
    blank_psnr: float


def _validate(
    model: torch.nn.Module, val_split: DatasetSplit, ray_bounds: RayBounds, run: RunFolder, iteration: int,
    train_seconds: float,
) -> _ViewScore:
    """Render one validation view (cycling through them) and log its PSNR next to the blank
    image's; the render becomes RUN/preview.png for anyone watching."""
    view = (iteration // max(1, model.config.validate_every)) % len(val_split)
    image = render_image(model, val_split.intrinsics, val_split.poses[view], ray_bounds)
    target = val_split.rgb_on_white(view).numpy()
    score = _ViewScore(iteration, psnr(image.rgb, target), blank_psnr(target))
    write_png(run.path / "preview.png", image.rgb)
    run.log_event("val", iteration=iteration, psnr=score.psnr, blank_psnr=score.blank_psnr, view=view,
                  elapsed_s=train_seconds)
    return score
