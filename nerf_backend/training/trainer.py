"""The training loop: batches of random rays, coarse + fine photometric loss, Adam with
exponential learning-rate decay, validation as it goes, atomic checkpoints, resume and
cancel (SIGINT/SIGTERM finish the step, save, and stop)."""

from __future__ import annotations

import shutil
import signal
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F

from nerf_contract import training_events as events
from nerf_contract.dataset_layout import transforms_name
from nerf_contract.run_layout import PREVIEW_NAME

from ..configs.presets import DEFAULT_PRESET, preset_config
from ..configs.train_config import SCHEDULES, TrainConfig, with_overrides
from ..core.cameras import camera_rays, pixel_centres
from ..core.devices import autocast_dtype, resolve_device
from ..core.errors import NerfError, RunError
from ..core.files import write_png
from ..core.progress import Progress
from ..core.stage_timer import count, stage
from ..data.dataset import DatasetSplit, composite, load_scene_bounds, load_scene_profile, load_split
from ..data.image_pyramid import ImageLevel, ImagePyramid, level_factor
from ..data.occupancy_prior import PRIOR_KINDS, OccupancyPrior, load_occupancy_prior
from ..data.run_folder import IN_USE, LOCK_NAME, RunFolder
from ..evaluation.render_views import render_image
from ..metrics.image_metrics import mse_to_psnr, psnr
from ..model_components.ray_bounds import RayBounds, choose_ray_bounds
from ..models.base import Model
from ..models.registry import build_model, model_class
from .auto import AVAILABLE_PRIOR, PRIOR_KIND, auto_config, pixel_footprint
from .collapse_guard import CollapseGuard, Verdict, blank_psnr, recovery_config
from .error_map import ErrorMap
from .sparse_adam import RowSparseAdam
from .sparse_grid_size import sparse_grid_size
from .surface_opacity import surface_opacity
from .surface_softness import surface_softness


@dataclass
class TrainOptions:
    dataset: Path
    run: Path
    preset: str | None = None  # None: DEFAULT_PRESET for a new run, the run's own on resume
    iterations: int | None = None  # total for the run; None: the preset's
    max_seconds: float | None = None  # total training seconds for the run
    # The time budget the schedule is laid over (TrainConfig.schedule); None: max_seconds.
    # The bench stops a run at points along its budget to score it, on one schedule.
    schedule_seconds: float | None = None
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
    # Throughput over the run's training time: rays, and samples the field was evaluated at
    # with gradients (None: a checkpoint written before they were counted).
    rays_per_second: float | None = None
    samples_per_second: float | None = None

    def throughput_words(self) -> str:
        """``rays_per_second`` and ``samples_per_second`` for people ("" when not counted).

        Example:
            >>> TrainSummary(10, 2.0, "time", None, rays_per_second=20480.0, samples_per_second=3.1e5).throughput_words()
            '20 480 rays and 0.31 M samples a second'
        """
        if self.rays_per_second is None or self.samples_per_second is None:
            return ""
        return f"{self.rays_per_second:,.0f} rays and {self.samples_per_second / 1e6:.2f} M samples a second".replace(
            ",", " ")

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
    return load_split(dataset, "val") if (dataset / transforms_name("val")).exists() else None


def sample_ray_batch(
    rgba: torch.Tensor, batch: int, generator: torch.Generator, precrop_fraction: float | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random (image, pixel) indices into images ``rgba [N, H, W, 4]``: ``image [B]`` and
    row-major ``pixel [B]``, drawn from the central ``precrop_fraction`` of each image when given."""
    count, height, width = rgba.shape[:3]
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


def _optimizer(model: Model, config: TrainConfig) -> torch.optim.Optimizer:
    """Adam over the model's own parameter groups, each at the learning-rate setting it names
    (``initial_lr`` is what decay scales)."""
    groups = [group for group in model.parameter_groups() if group.parameters]
    rates = [getattr(config, group.learning_rate) for group in groups]
    settings = [{"params": group.parameters, "initial_lr": rate, "lr": rate} for group, rate in zip(groups, rates)]
    # The fused kernel: one pass over each parameter's p, g, m and v instead of a pass per
    # operation (bench-step: 2.7 against 19 ms a step for a 256³ grid's 8 M parameters on 2
    # CPU cores). A device without it takes the plain one. On the CPU the grids' rows are
    # updated only where a step touched them (training/sparse_adam.py).
    adam = dict(betas=config.adam_betas, eps=config.adam_eps)
    if next(model.parameters()).device.type == "cpu":
        grids = [module for module in model.modules() if hasattr(module, "sparse_row_parameters")]
        return RowSparseAdam(settings, grids=grids, **adam, fused=True)
    try:
        return torch.optim.Adam(settings, **adam, fused=True)
    except RuntimeError:
        return torch.optim.Adam(settings, **adam)


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
    schedule_seconds: float | None  # the budget the schedule spans (None: by iterations)
    stop_at_iterations: bool  # False: a time budget alone ends the run
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
            "schedule_seconds": self.schedule_seconds,
            "stop_at_iterations": self.stop_at_iterations,
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
        stop_at_iterations = options.iterations is not None or stored.get("stop_at_iterations", True)
        schedule_seconds = options.schedule_seconds or options.max_seconds or stored.get("schedule_seconds")
    else:
        config = with_overrides(preset_config(options.preset or DEFAULT_PRESET), list(options.overrides))
        seed = options.seed
        max_seconds = options.max_seconds
        # A time budget alone trains until the time is spent (the schedule laid over it);
        # with --iters as well, whichever comes first.
        stop_at_iterations = options.iterations is not None or max_seconds is None
        schedule_seconds = options.schedule_seconds or max_seconds
    if config.schedule not in SCHEDULES:
        raise NerfError(f"schedule {config.schedule!r}: choose {' or '.join(SCHEDULES)}")
    if config.schedule == "iterations":
        schedule_seconds = None
    if options.iterations is not None:
        config = replace(config, iterations=options.iterations)

    if config.max_train_views is not None and config.max_train_views < len(train_split):
        train_split = train_split.subset(config.max_train_views)
    ray_bounds, bounds_reason = choose_ray_bounds(config.ray_bounds, load_scene_bounds(dataset))
    decisions = {"ray_bounds": {**ray_bounds.describe(), "reason": bounds_reason}}
    if options.resume:
        decisions = stored.get("decisions", decisions)
    else:
        user_set = frozenset(assignment.partition("=")[0] for assignment in options.overrides)
        if config.preset == "auto":
            config, shaped = auto_config(config, train_split, ray_bounds.box, load_scene_profile(dataset), user_set,
                                         schedule_seconds)
            decisions.update(shaped)
        elif config.model == "surface":
            config, shaped = surface_softness(config, train_split, ray_bounds.box, user_set)
            decisions.update(shaped)
        if config.model == "plenoxels":  # its own preset, or auto's model set to it with --set
            config, shaped = sparse_grid_size(config, train_split, ray_bounds.box, load_scene_profile(dataset),
                                              user_set)
            decisions.update(shaped)
    prior = _occupancy_prior(dataset, config)
    if not options.resume and config.model == "surface":
        config, shaped = surface_opacity(config, prior, user_set)
        decisions.update(shaped)
    return _RunPlan(dataset, config, seed, max_seconds, schedule_seconds, stop_at_iterations, device, train_split,
                    ray_bounds, prior, decisions)


def _train_locked(run: RunFolder, plan: _RunPlan, val_split: DatasetSplit | None, options: TrainOptions) -> TrainSummary:
    # The checkpoint first: a resume it refuses (damaged, or holding code) leaves the run as it was.
    state = run.load_checkpoint(plan.device) if options.resume and run.checkpoint_path.exists() else None
    training = _Training(run, plan, val_split, options)
    if state is not None:
        training.restore(state)
    return training.run()


class _Training:
    """One call of ``train``: the model, its optimiser and random generators, the counters,
    and the steps of the loop (``run``), each a method."""

    def __init__(self, run: RunFolder, plan: _RunPlan, val_split: DatasetSplit | None, options: TrainOptions) -> None:
        self.run_folder, self.plan, self.val_split, self.options = run, plan, val_split, options
        self.config = plan.config
        self.device = plan.device
        self.record = plan.record()
        run.write_config(self.record)
        self.amp_dtype = autocast_dtype(self.config.precision, self.device)
        # float16's narrow range needs the loss scaled so small gradients do not flush to zero.
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=self.amp_dtype is torch.float16)
        # A run that collapsed starts again at `start_iteration` and `start_seconds` (its
        # schedules count from there); `attempt` counts those starts.
        self.restart = {"attempt": 0, "start_iteration": 0, "start_seconds": 0.0}
        self.model = _new_model(self.config, plan.ray_bounds, plan.prior, plan.seed, 0, self.device)
        self.optimizer = _optimizer(self.model, self.config)
        self.batch_generator = torch.Generator().manual_seed(plan.seed)
        self.sample_generator = torch.Generator(device=self.device).manual_seed(plan.seed + 1)
        self.iteration, self.train_seconds = 0, 0.0
        self.trained = {"rays": 0, "samples": 0}  # over the run, resumed segments included
        self.images = ImagePyramid(plan.train_split.rgba.to(self.device), plan.train_split.intrinsics)
        # Coarse-to-fine images: the size of a full-size pixel on the scene, which each level's
        # pixels are measured against (None: always the full size).
        self.pixel_size = (pixel_footprint(plan.train_split, plan.ray_bounds.box)
                           if self.config.coarse_images and plan.ray_bounds.box is not None else None)
        self.image_factor = 1  # the downsampling of the last step's images
        self.poses = plan.train_split.poses.to(self.device)
        self.error_map = (ErrorMap(len(plan.train_split.poses), share=self.config.error_sampling)
                          if self.config.error_sampling > 0 else None)
        self.score: _ViewScore | None = None
        self.collapse: Verdict | None = None
        self.guard = CollapseGuard(val_split, plan.ray_bounds, self.config.collapse_margin_db)
        self.progress: _TrainingProgress | None = None

    def restore(self, state: dict) -> None:
        """Continue from a checkpoint: weights (at the shapes they were saved with), the
        optimiser built for them, generators and counters."""
        self.restart = state.get("restart", self.restart)
        self.model.restore(state["model"])
        self.optimizer = _optimizer(self.model, self.config)
        self.optimizer.load_state_dict(state["optimizer"])
        if "grad_scaler" in state:
            self.scaler.load_state_dict(state["grad_scaler"])
        # A generator's state is a CPU byte tensor, a CUDA generator's too; loading the
        # checkpoint onto the GPU moved them there.
        self.batch_generator.set_state(state["batch_rng"].cpu())
        self.sample_generator.set_state(state["sample_rng"].cpu())
        self.iteration, self.train_seconds = state["iteration"], state["train_seconds"]
        self.trained = state.get("trained", {"rays": None, "samples": None})

    def run(self) -> TrainSummary:
        config, run, options = self.config, self.run_folder, self.options
        started_at = self.iteration
        run.log(events.Start(iteration=self.iteration, resumed=options.resume, preset=config.preset,
                             device=str(self.device), cpu_threads=torch.get_num_threads(),
                             target_iterations=config.iterations if self.plan.stop_at_iterations else None,
                             max_seconds=self.plan.max_seconds, schedule_seconds=self.plan.schedule_seconds))
        self.progress = _TrainingProgress(config.iterations, self.iteration, self.plan.max_seconds,
                                          self.train_seconds, enabled=options.progress,
                                          description=f"train {config.preset}")
        stop_reason = self._loop()
        self.progress.close()
        if self.val_split is not None and stop_reason != "collapsed":
            stop_reason = self._final_validation(stop_reason)
        self._checkpoint()
        val_psnr = self.score.psnr if self.score is not None else None
        run.log(events.Done(iteration=self.iteration, elapsed_s=self.train_seconds, reason=stop_reason,
                            val_psnr=val_psnr))
        per_second = {key: None if value is None or self.train_seconds <= 0 else value / self.train_seconds
                      for key, value in self.trained.items()}
        return TrainSummary(self.iteration, self.train_seconds, stop_reason, val_psnr, collapse=self.collapse,
                            started_at=started_at, rays_per_second=per_second["rays"],
                            samples_per_second=per_second["samples"])

    def _loop(self) -> str:
        """Steps until the iterations or the time budget are spent, a stop is asked for, or
        the model collapses for good; returns why it stopped."""
        max_seconds = self.plan.max_seconds
        self.model.train()
        with _StopRequest() as stop:
            while not self.plan.stop_at_iterations or self.iteration < self.config.iterations:
                if max_seconds is not None and self.train_seconds >= max_seconds:
                    return "time"
                if stop.requested:
                    return "cancelled"
                self._step()
                if self.val_split is not None and self.iteration % self.config.validate_every == 0:
                    self._validate()
                    if self._judged() and not self._survives_collapse_check():
                        return "collapsed"
                if self.iteration % self.config.checkpoint_every == 0:
                    self._checkpoint()
        return "iterations"

    def _step(self) -> None:
        """One optimiser step on a batch of random rays."""
        config, device, model = self.config, self.device, self.model
        steps = self.iteration - self.restart["start_iteration"]
        scheduled = self._scheduled_step(steps)
        # Before the clock: making a downsampled level is loading, once a level (0.5-1 s for
        # 100 views at 800×800 on 2 CPU cores), as reading the dataset is.
        images = self._images()
        step_start = time.perf_counter()
        precrop = config.precrop_fraction if scheduled < config.precrop_iterations else None
        rays = config.rays_per_batch
        with stage("data", items=rays):
            width, height = images.intrinsics.width, images.intrinsics.height
            if self.error_map is not None and precrop is None:
                image_index, pixel_index = self.error_map.sample(rays, height, width, self.batch_generator)
            else:
                image_index, pixel_index = sample_ray_batch(images.rgba, rays, self.batch_generator, precrop)
            image_index, pixel_index = image_index.to(device), pixel_index.to(device)
            pixels_rgba = images.rgba[image_index, pixel_index // width, pixel_index % width]
            if config.random_background:
                background = torch.rand((len(pixel_index), 3), generator=self.batch_generator).to(device)
            else:
                background = torch.ones((), device=device)
            target = composite(pixels_rgba, background)
        with stage("rays", items=rays):
            origins, directions = camera_rays(images.intrinsics, self.poses[image_index],
                                              pixel_centres(width, pixel_index))
            t_near, t_far = self.plan.ray_bounds(origins, directions)
        with stage("upkeep"):  # the model's schedule: grid growth, occupancy refreshes
            if model.before_step(steps, scheduled, self._steps_left()):
                self.optimizer = _optimizer(model, config)  # the parameters were replaced (a grid upsampled)
            note = model.take_note()
            if note is not None:
                self.progress.note(note)
            # After any rebuild: a new optimiser starts at the initial rates.
            decay = config.learning_rate_decay(scheduled)
            for group in self.optimizer.param_groups:
                group["lr"] = group["initial_lr"] * decay
        with torch.autocast(device.type, dtype=self.amp_dtype or torch.float32, enabled=self.amp_dtype is not None):
            outputs = model(origins, directions, t_near, t_far, background=background,
                            generator=self.sample_generator)
        with stage("loss", items=rays):
            errors = [F.mse_loss(output.rgb.float(), target) for output in outputs]
            loss = torch.stack(errors).sum()
            if self.error_map is not None:
                ray_errors = (outputs[-1].rgb.detach().float() - target).square().mean(dim=-1)
                self.error_map.update(image_index, pixel_index, height, width, ray_errors)
            regularisation = model.regularisation(self.sample_generator)
            if regularisation is not None:  # a field's own terms (the surface field's eikonal)
                loss = loss + regularisation
            # Reading the loss waits for the device: on a GPU only when the step is logged
            # (a non-finite weight is caught before any checkpoint all the same).
            if (device.type == "cpu" or (self.iteration + 1) % config.log_every == 0) and not torch.isfinite(loss):
                self._diverged(f"loss {loss.item()}")
        def parameters() -> int:  # counted only while profiling
            return sum(p.numel() for p in model.parameters())

        def updated() -> int:  # values the optimiser read and wrote (a row-sparse one: fewer)
            floats = getattr(self.optimizer, "floats_updated", None)
            return parameters() if floats is None else floats

        with stage("backward", items=parameters):
            self.optimizer.zero_grad(set_to_none=True)
            self.scaler.scale(loss).backward()
        with stage("optimiser", items=updated):
            self.scaler.step(self.optimizer)
            self.scaler.update()
            model.after_step()
        count("grid values", lambda: getattr(self.optimizer, "row_floats_updated", None) or 0)
        self._count_trained(rays, outputs)
        self.iteration += 1
        self.train_seconds += time.perf_counter() - step_start
        self.progress.step(self.iteration, self.train_seconds)
        if self.iteration % config.log_every == 0 or self.iteration == config.iterations:
            batch_psnr = mse_to_psnr(errors[-1].item())
            self.progress.show(loss=f"{loss.item():.4f}", psnr=f"{batch_psnr:.2f}")
            self.run_folder.log(events.Train(iteration=self.iteration, loss=loss.item(), psnr=batch_psnr,
                                             lr=config.learning_rate_at(scheduled), scheduled=scheduled,
                                             image_size=[images.intrinsics.width, images.intrinsics.height],
                                             elapsed_s=self.train_seconds))

    def _images(self) -> ImageLevel:
        """The training images at the size the model's detail asks for now: downsampled
        while a grid is still coarse (``coarse_images``), full size once it holds its final
        detail. A change of size is said above the progress bar."""
        full = self.images.full.intrinsics
        detail = self.model.coarse_detail() if self.pixel_size is not None else None
        factor = 1 if detail is None else level_factor(self.pixel_size, detail, full.width, full.height)
        level = self.images.level(factor)
        if factor != self.image_factor:
            size = f"{level.intrinsics.width}×{level.intrinsics.height}"
            self.progress.note(f"training on {size} images"
                               + (f" (1/{factor} size, the model's detail)" if factor > 1 else " (full size)"))
            self.image_factor = factor
        return level

    def _count_trained(self, rays: int, outputs: list) -> None:
        """Adds a step's rays and the samples its field was evaluated at (a march's lit ones,
        else every one of each pass) to the run's counts, unless its checkpoint predates them."""
        if self.trained["rays"] is None:
            return
        self.trained["rays"] += rays
        self.trained["samples"] += sum(output.field_samples if output.field_samples is not None
                                       else output.weights.numel() if output.weights is not None else 0
                                       for output in outputs)

    def _steps_left(self) -> float | None:
        """Under a time budget, the steps the run can still take at its rate so far (the whole
        run's, so a resumed run knows it at once); None by iterations or before any step."""
        budget = self.plan.schedule_seconds
        if budget is None or self.train_seconds <= 0:
            return None
        left = self.iteration / self.train_seconds * max(budget - self.train_seconds, 0.0)
        if self.plan.stop_at_iterations:
            left = min(left, self.config.iterations - self.iteration)
        return left

    def _scheduled_step(self, steps: int) -> int:
        """Where this start of the run is in its schedule after ``steps`` steps: by the
        share of the schedule's time budget spent, when it has one (TrainConfig.schedule)."""
        budget, start = self.plan.schedule_seconds, self.restart.get("start_seconds", 0.0)
        spent = None if budget is None else (self.train_seconds - start) / max(budget - start, 1e-9)
        return self.config.scheduled_step(steps, spent, self.plan.stop_at_iterations)

    def _validate(self) -> None:
        self.score = _validate(self.model, self.val_split, self.plan.ray_bounds, self.run_folder, self.iteration,
                               self.train_seconds, self.config.validate_every)

    def _judged(self) -> bool:
        """Whether this start of the run is old enough for the collapse guard to judge."""
        return self.iteration - self.restart["start_iteration"] >= self.config.collapse_check_after

    def _survives_collapse_check(self) -> bool:
        """After a validation: False when the model has collapsed and cannot start again."""
        self.collapse = self.guard.confirm(self.model, self.score.psnr, self.score.blank_psnr, self.iteration)
        return self.collapse is None or self._restart_after_collapse()

    def _final_validation(self, stop_reason: str) -> str:
        """Validate the model as it ends (unless the last step just did). A run old enough to
        judge never ends silently on a near-blank model; nor does one restarted after a
        collapse, however young (a young first start is not yet called a failure: it may
        simply not have started)."""
        if self.score is None or self.score.iteration != self.iteration:
            self._validate()
        judged = self._judged() or self.restart["attempt"] >= 1
        self.collapse = (self.guard.confirm(self.model, self.score.psnr, self.score.blank_psnr, self.iteration)
                         if judged else None)
        if self.collapse is None:
            return stop_reason
        self._report_collapse(self.collapse, f"none: the run ended ({stop_reason}) before it could recover", final=True)
        return "collapsed"

    def _restart_after_collapse(self) -> bool:
        """After a collapse: start again once with the recovery config (True), else stop."""
        if self.restart["attempt"] >= 1:
            self._report_collapse(self.collapse, "stopped: it had already been restarted once", final=True)
            return False
        transparent = bool((self.images.full.rgba[..., 3] < 255).any())
        self.config, changes, reasons = recovery_config(self.config, has_transparency=transparent)
        action = "restarted from a new start with " + "; ".join(reasons)
        self.plan.decisions["collapse_recovery"] = {"value": changes, "at_iteration": self.iteration,
                                                    "reason": f"{self.collapse.describe()}: {action}"}
        self.restart.update(attempt=self.restart["attempt"] + 1, start_iteration=self.iteration,
                            start_seconds=self.train_seconds)
        self.run_folder.write_config({**self.record, "config": self.config.to_dict(),
                                      "decisions": self.plan.decisions})
        self.model = _new_model(self.config, self.plan.ray_bounds, self.plan.prior, self.plan.seed,
                                self.restart["attempt"], self.device)
        self.optimizer = _optimizer(self.model, self.config)
        self._report_collapse(self.collapse, action, final=False)
        return True

    def _report_collapse(self, verdict: Verdict, action: str, final: bool) -> None:
        self.run_folder.log(events.Collapse(
            iteration=verdict.iteration, elapsed_s=self.train_seconds, val_psnr=verdict.psnr,
            blank_psnr=verdict.blank_psnr, margin_db=verdict.margin_db, views=list(verdict.views), action=action,
            reason=verdict.describe(), final=final))
        self.progress.note(f"collapse: {verdict.describe()}; {action}")

    def _checkpoint(self) -> None:
        # A non-finite weight never replaces the last good checkpoint.
        broken = [name for name, value in self.model.state_dict().items()
                  if value.is_floating_point() and not bool(torch.isfinite(value).all())]
        if broken:
            self._diverged(f"weights {', '.join(broken[:3])} are not finite")
        self.run_folder.save_checkpoint({
            "iteration": self.iteration, "train_seconds": self.train_seconds, "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(), "batch_rng": self.batch_generator.get_state(),
            "sample_rng": self.sample_generator.get_state(), "config": self.config.to_dict(),
            "restart": self.restart, "trained": self.trained,
            **({"grad_scaler": self.scaler.state_dict()} if self.scaler.is_enabled() else {}),
        })
        self.run_folder.log(events.Checkpoint(iteration=self.iteration, elapsed_s=self.train_seconds,
                                              path=str(self.run_folder.checkpoint_path)))

    def _diverged(self, what: str) -> None:
        run = self.run_folder
        kept = (f"the last good checkpoint is kept at {run.checkpoint_path}" if run.checkpoint_path.exists()
                else "no checkpoint had been written yet")
        message = (f"training diverged at iteration {self.iteration} ({what}); {kept}; "
                   f"try a lower learning_rate (--set learning_rate=...)")
        run.log(events.Error(iteration=self.iteration, message=message))
        raise NerfError(message)


def _occupancy_prior(dataset: Path, config: TrainConfig) -> OccupancyPrior | None:
    """The dataset's occupancy prior of the kind ``config`` asks for (grid models only)."""
    if not model_class(config.model).uses_occupancy_prior or config.occupancy_prior == "none":
        return None
    if config.occupancy_prior == AVAILABLE_PRIOR:
        return load_occupancy_prior(dataset, PRIOR_KIND)
    if config.occupancy_prior not in PRIOR_KINDS:
        raise NerfError(f"occupancy_prior {config.occupancy_prior!r}: choose none, {AVAILABLE_PRIOR}, "
                        f"{', '.join(PRIOR_KINDS)}")
    prior = load_occupancy_prior(dataset, config.occupancy_prior)
    if prior is None:
        raise NerfError(f"{dataset}: occupancy_prior={config.occupancy_prior} asked for, but the dataset has no "
                        f"occupancy prior (scene_profile.json names none); use occupancy_prior=none")
    return prior


def _new_model(config: TrainConfig, ray_bounds: RayBounds, prior: OccupancyPrior | None, seed: int, attempt: int,
               device: torch.device) -> Model:
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
    model: Model, val_split: DatasetSplit, ray_bounds: RayBounds, run: RunFolder, iteration: int,
    train_seconds: float, validate_every: int,
) -> _ViewScore:
    """Render one validation view (cycling through them) and log its PSNR next to the blank
    image's; the render becomes RUN/preview.png for anyone watching."""
    view = (iteration // max(1, validate_every)) % len(val_split)
    image = render_image(model, val_split.intrinsics, val_split.poses[view], ray_bounds)
    target = val_split.rgb_on_white(view).numpy()
    score = _ViewScore(iteration, psnr(image.rgb, target), blank_psnr(target))
    write_png(run.path / PREVIEW_NAME, image.rgb)
    run.log(events.Val(iteration=iteration, psnr=score.psnr, blank_psnr=score.blank_psnr, view=view,
                       elapsed_s=train_seconds))
    return score
