"""The training loop of a planned run (``planning/``): batches of random rays, coarse + fine
photometric loss, Adam with exponential learning-rate decay, validation as it goes, atomic
checkpoints, resume and cancel (SIGINT/SIGTERM finish the step, save, and stop). It runs the
plan and decides nothing; the one change a run makes to its plan as it goes is the collapse
guard's recovery (``collapse_guard.recovery_config``), recorded in ``config.json``."""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F

from nerf_contract import training_events as events

from ..configs.train_config import TrainConfig
from ..core.cameras import camera_rays, pixel_centres
from ..core.devices import autocast_dtype
from ..core.errors import NerfError
from ..core.stage_timer import count, stage
from ..core.stop_request import StopRequest
from ..data.image_pyramid import ImageLevel, ImagePyramid, level_factor
from ..data.occupancy_prior import OccupancyPrior
from ..data.run_folder import RunFolder
from ..metrics.image_metrics import mse_to_psnr
from ..model_components.ray_bounds import RayBounds
from ..models.base import Model
from ..models.registry import build_model
from ..planning.facts import RunFacts, RunRequest, gather_facts
from ..planning.plan import RunPlan, plan_run
from ..planning.rules import RULES
from .checkpoint_writer import CheckpointWriter
from .collapse_guard import CollapseGuard, Verdict, recovery_config
from .error_map import ErrorMap
from .optimizer import make_optimizer
from .pauses import PauseCadence
from .progress_bar import TrainingProgress
from .ray_batch import draw_batch
from .summary import TrainSummary
from .validation import ViewScore, validate_view


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

    def request(self) -> RunRequest:
        """What these options ask of the run's plan."""
        return RunRequest(self.preset, tuple(self.overrides), self.iterations, self.max_seconds,
                          self.schedule_seconds, self.seed, self.device, self.resume)


def train(options: TrainOptions) -> TrainSummary:
    request = options.request()
    run = RunFolder(options.run)
    run.refuse_to_replace(options.resume, options.overwrite)  # before the lock: a refused folder gains no lock file
    # Read the whole dataset and settle the run before touching its folder: bad input
    # (a broken dataset, a bad --set, a missing prior) leaves nothing behind.
    facts = gather_facts(Path(options.dataset), run, request, with_val=options.validate)
    plan = plan_run(facts, RULES)
    with run.claimed(options.resume, options.overwrite):
        # The checkpoint first: a resume it refuses (damaged, or holding code) leaves the run as it was.
        state = run.load_checkpoint(plan.device) if options.resume and run.checkpoint_path.exists() else None
        training = _Training(run, plan, facts, options)
        if state is not None:
            training.restore(state)
        return training.run()


class _Training:
    """One call of ``train``: the model, its optimiser and random generators, the counters,
    and the steps of the loop (``run``), each a method."""

    def __init__(self, run: RunFolder, plan: RunPlan, facts: RunFacts, options: TrainOptions) -> None:
        self.run_folder, self.plan, self.val_split, self.options = run, plan, facts.val_split, options
        self.config = plan.config
        self.device = plan.device
        run.write_config(plan.record())
        views = facts.train_split.subset(plan.train_views)
        self.prior = facts.priors.get(plan.prior_kind) if plan.prior_kind else None
        self.amp_dtype = autocast_dtype(self.config.precision, self.device)
        # float16's narrow range needs the loss scaled so small gradients do not flush to zero.
        self.scaler = torch.amp.GradScaler(self.device.type, enabled=self.amp_dtype is torch.float16)
        # A run that collapsed starts again at `start_iteration` and `start_seconds` (its
        # schedules count from there); `attempt` counts those starts.
        self.restart = {"attempt": 0, "start_iteration": 0, "start_seconds": 0.0}
        self.model = _new_model(self.config, plan.ray_bounds, self.prior, plan.seed, 0, self.device)
        self.optimizer = make_optimizer(self.model, self.config)
        self.batch_generator = torch.Generator().manual_seed(plan.seed)
        self.sample_generator = torch.Generator(device=self.device).manual_seed(plan.seed + 1)
        self.iteration, self.train_seconds = 0, 0.0
        self.trained = {"rays": 0, "samples": 0}  # over the run, resumed segments included
        self.images = ImagePyramid(views.rgba.to(self.device), views.intrinsics)
        self.image_factor = 1  # the downsampling of the last step's images
        self.poses = views.poses.to(self.device)
        self.error_map = (ErrorMap(len(views), share=self.config.error_sampling)
                          if self.config.error_sampling > 0 else None)
        self.score: ViewScore | None = None
        self.validations = 0  # this session's: each shows the next validation view
        self.judged_start = -1  # the start of the run (restart["attempt"]) the guard last judged
        self.checkpoints = CheckpointWriter(run)
        self.collapse: Verdict | None = None
        self.guard = CollapseGuard(facts.val_split, plan.ray_bounds, self.config.collapse_margin_db)
        self.progress: TrainingProgress | None = None

    def restore(self, state: dict) -> None:
        """Continue from a checkpoint: weights (at the shapes they were saved with), the
        optimiser built for them, generators and counters."""
        self.restart = state.get("restart", self.restart)
        self.model.restore(state["model"])
        self.optimizer = make_optimizer(self.model, self.config)
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
        self.progress = TrainingProgress(config.iterations, self.iteration, self.plan.max_seconds,
                                          self.train_seconds, enabled=options.progress,
                                          description=f"train {config.preset}")
        stop_reason = self._loop()
        self.progress.close()
        if self.val_split is not None and stop_reason != "collapsed":
            stop_reason = self._final_validation(stop_reason)
        self._checkpoint()
        self.checkpoints.finish()  # its event before the run's last
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
        max_seconds, config = self.plan.max_seconds, self.config
        validating = PauseCadence(config.validate_every, config.pause_share)
        checkpointing = PauseCadence(config.checkpoint_every, config.pause_share)
        self.model.train()
        with StopRequest() as stop:
            while not self.plan.stop_at_iterations or self.iteration < self.config.iterations:
                if max_seconds is not None and self.train_seconds >= max_seconds:
                    return "time"
                if stop.requested:
                    return "cancelled"
                self._step()
                if self.val_split is not None and (validating.due(self.iteration, self.train_seconds) or (
                        validating.on_cadence(self.iteration) and self._guard_waits())):
                    self._paused(validating, self._validate)
                    if self._judged() and not self._survives_collapse_check():
                        return "collapsed"
                if checkpointing.due(self.iteration, self.train_seconds):
                    self._paused(checkpointing, self._checkpoint)
        return "iterations"

    def _paused(self, cadence: PauseCadence, work: Callable[[], None]) -> None:
        started = time.perf_counter()
        work()
        cadence.took(time.perf_counter() - started, self.train_seconds)

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
            batch = draw_batch(images, rays, self.batch_generator, precrop, self.error_map, config.random_background,
                               device)
        with stage("rays", items=rays):
            origins, directions = camera_rays(images.intrinsics, self.poses[batch.image],
                                              pixel_centres(images.intrinsics.width, batch.pixel))
            t_near, t_far = self.plan.ray_bounds(origins, directions)
        with stage("upkeep"):  # the model's schedule: grid growth, occupancy refreshes
            if model.before_step(steps, scheduled, self._steps_left()):
                self.optimizer = make_optimizer(model, config)  # the parameters were replaced (a grid upsampled)
            note = model.take_note()
            if note is not None:
                self.progress.note(note)
            # After any rebuild: a new optimiser starts at the initial rates.
            decay = config.learning_rate_decay(scheduled)
            for group in self.optimizer.param_groups:
                group["lr"] = group["initial_lr"] * decay
        with torch.autocast(device.type, dtype=self.amp_dtype or torch.float32, enabled=self.amp_dtype is not None):
            outputs = model(origins, directions, t_near, t_far, background=batch.background,
                            generator=self.sample_generator)
        with stage("loss", items=rays):
            errors = [F.mse_loss(output.rgb.float(), batch.target) for output in outputs]
            loss = torch.stack(errors).sum()
            if self.error_map is not None:
                ray_errors = (outputs[-1].rgb.detach().float() - batch.target).square().mean(dim=-1)
                self.error_map.update(batch.image, batch.pixel, images.intrinsics.height, images.intrinsics.width,
                                      ray_errors)
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
        pixel = self.plan.coarse_image_pixel
        detail = self.model.coarse_detail() if pixel is not None else None
        factor = 1 if detail is None else level_factor(pixel, detail, full.width, full.height)
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
        self.score = validate_view(self.model, self.val_split, self.plan.ray_bounds, self.run_folder, self.iteration,
                                   self.train_seconds, self.validations % len(self.val_split))
        self.validations += 1

    def _guard_waits(self) -> bool:
        """Whether this start of the run is old enough to judge and not yet judged: its first
        judgement is never put off (a model that collapsed from the start restarts at
        ``collapse_check_after`` steps, on any machine); later ones come with the spaced
        validations."""
        return self._judged() and self.judged_start != self.restart["attempt"]

    def _judged(self) -> bool:
        """Whether this start of the run is old enough for the collapse guard to judge."""
        return self.iteration - self.restart["start_iteration"] >= self.config.collapse_check_after

    def _survives_collapse_check(self) -> bool:
        """After a validation: False when the model has collapsed and cannot start again."""
        self.judged_start = self.restart["attempt"]
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
        recovery = {"value": changes, "at_iteration": self.iteration, "reason": f"{self.collapse.describe()}: {action}"}
        self.plan = dataclasses.replace(self.plan, config=self.config,
                                        decisions={**self.plan.decisions, "collapse_recovery": recovery})
        self.restart.update(attempt=self.restart["attempt"] + 1, start_iteration=self.iteration,
                            start_seconds=self.train_seconds)
        self.run_folder.write_config(self.plan.record())
        self.model = _new_model(self.config, self.plan.ray_bounds, self.prior, self.plan.seed,
                                self.restart["attempt"], self.device)
        self.optimizer = make_optimizer(self.model, self.config)
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
        self.checkpoints.save({
            "iteration": self.iteration, "train_seconds": self.train_seconds, "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(), "batch_rng": self.batch_generator.get_state(),
            "sample_rng": self.sample_generator.get_state(), "config": self.config.to_dict(),
            "restart": self.restart, "trained": self.trained,
            **({"grad_scaler": self.scaler.state_dict()} if self.scaler.is_enabled() else {}),
        }, events.Checkpoint(iteration=self.iteration, elapsed_s=self.train_seconds,
                             path=str(self.run_folder.checkpoint_path)))

    def _diverged(self, what: str) -> None:
        run = self.run_folder
        with contextlib.suppress(NerfError):  # a checkpoint still being written is then on disk
            self.checkpoints.finish()
        kept = (f"the last good checkpoint is kept at {run.checkpoint_path}" if run.checkpoint_path.exists()
                else "no checkpoint had been written yet")
        message = (f"training diverged at iteration {self.iteration} ({what}); {kept}; "
                   f"try a lower learning_rate (--set learning_rate=...)")
        run.log(events.Error(iteration=self.iteration, message=message))
        raise NerfError(message)


def _new_model(config: TrainConfig, ray_bounds: RayBounds, prior: OccupancyPrior | None, seed: int, attempt: int,
               device: torch.device) -> Model:
    """A freshly initialised model; each restart after a collapse draws another initialisation."""
    torch.manual_seed(seed + 1000 * attempt)
    return build_model(config, ray_bounds.box, prior).to(device)
