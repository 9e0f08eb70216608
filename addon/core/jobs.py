"""Background jobs the add-on starts and watches: training and the asset's export (the
backend's own Python), dataset generation and the animation (a background Blender). Plain
Python, no bpy and no torch, so tests drive it without Blender; the panel only draws what
``poll()`` returns and calls these methods.

A job is found again from its folder alone (reopening the .blend): ``<folder>.job.json``
beside the run or dataset folder records the process id and command, and the run's
``events.jsonl`` (training) or the images on disk (datasets) say how far it got. The
process's output goes to ``<folder>.log`` beside it, whose tail explains a crash.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from datasets_gen.core.options import GeneratorOptions, options_to_argv
from nerf_contract import commands
from nerf_contract.dataset_layout import CYCLES_FRAMES_DIR, SPLITS, VIEW_PNG_GLOB, transforms_name
from nerf_contract.run_layout import (
    ANIMATION_FRAMES_DIR,
    ANIMATION_RECORD,
    ASSET_COMPLETE,
    ASSET_NAME,
    ASSET_RECORD_SUFFIX,
    ASSET_STAGES,
    ASSET_STAGES_DONE,
    EVENTS_NAME,
    PREVIEW_NAME,
)
from nerf_contract.training_events import Checkpoint, Collapse, Done, Error, Start, Train, Val, read_events

LOG_TAIL_LINES = 12


@dataclass
class JobStatus:
    """What the panel shows. ``state``: idle, running, done, cancelled, failed."""

    state: str
    fraction: float = 0.0  # 0..1 of the work
    detail: str = ""  # one line: iteration, PSNR, views...
    seconds_left: float | None = None
    psnr: float | None = None
    iteration: int | None = None
    error: str = ""  # failed: the tail of the process's output
    warning: str = ""  # something the user must see although the job goes on (a collapse and its recovery)
    extra: dict = field(default_factory=dict)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _tail(path: Path, lines: int = LOG_TAIL_LINES) -> str:
    if not path.is_file():
        return ""
    text = path.read_text(encoding="utf-8", errors="replace").splitlines()
    return "\n".join(line for line in text[-lines:] if line.strip())


class _Job:
    """A process started with its output in ``<folder>.log`` and its record in ``<folder>.job.json``."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self._process: subprocess.Popen | None = None

    @property
    def log_path(self) -> Path:
        return self.folder.with_name(self.folder.name + ".log")

    @property
    def record_path(self) -> Path:
        return self.folder.with_name(self.folder.name + ".job.json")

    def record(self) -> dict | None:
        try:
            return json.loads(self.record_path.read_text())
        except (OSError, json.JSONDecodeError):
            return None

    def _update(self, **fields) -> None:
        """Add ``fields`` to the job's record."""
        data = self.record() or {}
        data.update(fields)
        self.record_path.write_text(json.dumps(data))

    def _launch(self, command: list[str], env: dict[str, str] | None = None, cwd: Path | None = None) -> None:
        if self.is_running():
            raise RuntimeError(f"{self.folder}: a job is already running for this folder (pid {self.record()['pid']})")
        self.folder.parent.mkdir(parents=True, exist_ok=True)
        log = open(self.log_path, "w", encoding="utf-8")
        # A new session: Blender's Ctrl+C or closing does not reach it, and cancel is ours to send.
        options = {"start_new_session": True} if os.name != "nt" else {"creationflags": subprocess.CREATE_NEW_PROCESS_GROUP}
        self._process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                         env=env, cwd=cwd, **options)
        log.close()
        self.record_path.write_text(json.dumps({"pid": self._process.pid, "command": command, "started": time.time()}))

    def returncode(self) -> int | None:
        """The exit code when this object started the process and it has ended; else None."""
        return None if self._process is None else self._process.poll()

    def is_running(self) -> bool:
        if self._process is not None:
            return self._process.poll() is None
        record = self.record()
        return bool(record) and _process_alive(int(record["pid"]))

    def _signal(self, sig: int) -> None:
        record = self.record()
        if self._process is not None and self._process.poll() is None:
            self._process.send_signal(sig)
        elif record and _process_alive(int(record["pid"])):
            os.kill(int(record["pid"]), sig)

    def cancel(self) -> None:
        """Ask the job to stop (it finishes its step and saves first)."""
        self._signal(signal.SIGTERM if os.name != "nt" else signal.CTRL_BREAK_EVENT)

    def kill(self) -> None:
        """Stop at once, saving nothing (what a crash looks like)."""
        self._signal(signal.SIGKILL if os.name != "nt" else signal.SIGTERM)

    def wait(self, timeout: float | None = None) -> int | None:
        if self._process is not None:
            return self._process.wait(timeout)
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.is_running():
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"{self.folder}: job still running after {timeout} s")
            time.sleep(0.2)
        return None

    def _ended_badly(self, finished: bool, running: bool) -> JobStatus | None:
        """A failed status when the process is gone without finishing its work (``running``:
        whether it was alive when ``finished`` was decided, so that both describe one moment)."""
        code = self.returncode()
        if finished or running:
            return None
        if code is None and self.record() is None:
            return None  # never started here
        reason = f"exited with code {code}" if code is not None else "is no longer running"
        if code is not None and code < 0:
            reason = f"was killed by signal {-code}"
        tail = _tail(self.log_path)
        # The process's own last words first: they name the problem; the exit code is secondary.
        return JobStatus("failed", error=f"{tail}\n(the process {reason})" if tail else f"the process {reason}")


class TrainingJob(_Job):
    """``python -m nerf_backend train`` in the backend's Python, watched through the run's events."""

    def __init__(self, run: Path) -> None:
        super().__init__(run)

    @property
    def run(self) -> Path:
        return self.folder

    @property
    def preview_path(self) -> Path:
        return self.run / PREVIEW_NAME

    def start(self, python: str, backend_root: Path, dataset: Path, preset: str, iterations: int | None = None,
              max_seconds: float | None = None, device: str = "auto", resume: bool = False,
              overwrite: bool = False, cpu_threads: int | None = None) -> None:
        """Train in the backend's ``python``, with ``backend_root`` (the folder holding
        ``nerf_backend/``) on its path."""
        command = commands.backend_command(python, commands.train_argv(
            dataset, self.run, device=device, preset=preset, resume=resume, iterations=iterations,
            max_seconds=max_seconds, cpu_threads=cpu_threads, overwrite=overwrite))
        env = dict(os.environ, PYTHONPATH=str(backend_root), PYTHONUNBUFFERED="1")
        self._launch(command, env=env)

    def poll(self) -> JobStatus:
        running = self.is_running()  # before the events: a process that ends meanwhile has written them all
        events = read_events(self.run / EVENTS_NAME)
        done = [e for e in events if isinstance(e, Done)]
        starts = [e for e in events if isinstance(e, Start)]
        last_start = events.index(starts[-1]) if starts else 0
        # A run just resumed still shows its last session's "done" until the new one logs its
        # start: while the process lives, the run is running.
        finished = bool(done) and events.index(done[-1]) > last_start and not running
        failure = self._ended_badly(finished, running)
        errors = [e for e in events[last_start:] if isinstance(e, Error)]
        if failure is not None:
            if errors:
                failure.error = errors[-1].message + "\n" + failure.error
            return failure
        if not events and not running:
            return JobStatus("idle")
        start = starts[-1] if starts else Start()
        progress = [e for e in events if isinstance(e, (Train, Val, Checkpoint))]
        latest = progress[-1] if progress else None
        iteration = latest.iteration if latest else start.iteration
        elapsed = latest.elapsed_s if latest else 0.0
        target, budget = start.target_iterations, start.max_seconds
        fractions = [iteration / target if target else 0.0]
        if budget:
            fractions.append(elapsed / budget)
        fraction = min(1.0, max(fractions))
        vals = [e for e in events if isinstance(e, Val)]
        trains = [e for e in events if isinstance(e, Train)]
        psnr = vals[-1].psnr if vals else (trains[-1].psnr if trains else None)
        seconds_left = elapsed * (1 - fraction) / fraction if 0 < fraction < 1 else None
        detail = f"iteration {iteration}" + (f" of {target}" if target and not budget else "")
        if psnr is not None:
            detail += f", PSNR {psnr:.2f} dB" + (" (validation)" if vals else " (batch)")
        # The trainer's collapse guard: what it found and what it did (a restart, or the end).
        collapses = [e for e in events if isinstance(e, Collapse)]
        warning = (f"Collapsed at iteration {collapses[-1].iteration}: {collapses[-1].reason}; {collapses[-1].action}"
                   if collapses else "")
        if finished:
            reason = done[-1].reason
            if reason == "collapsed":
                return JobStatus("failed", fraction, detail, None, psnr, iteration,
                                 error=f"The model collapsed to the blank image. {warning}",
                                 extra={"reason": reason, "val_psnr": done[-1].val_psnr})
            state = "cancelled" if reason == "cancelled" else "done"
            return JobStatus(state, 1.0 if state == "done" else fraction, detail, None, psnr, iteration,
                             warning=warning, extra={"reason": reason, "val_psnr": done[-1].val_psnr})
        return JobStatus("running", fraction, detail, seconds_left, psnr, iteration, warning=warning)


def dataset_complete(folder: Path) -> bool:
    """Whether ``folder`` holds a finished dataset: every split's transforms JSON, which the
    generator writes last."""
    return all((Path(folder) / transforms_name(split)).is_file() for split in SPLITS)


class DatasetJob(_Job):
    """``blender -b SCENE --python datasets_gen/generate.py -- ...`` rendering a dataset,
    watched by counting the images written."""

    def __init__(self, out: Path) -> None:
        super().__init__(out)

    def start(self, blender: str, blend_file: Path, script: Path, options: GeneratorOptions) -> None:
        """Render ``blend_file`` with the generator's ``script`` and ``options``, into this job's
        folder (whatever ``options.out_dir`` says)."""
        options = replace(options, out_dir=str(self.folder))
        argv = [*options_to_argv(options), commands.GeneratorFlag.NO_PROGRESS]
        self._launch(commands.blender_script_command(blender, blend_file, script, argv))
        data = self.record() or {}
        data["views"] = {split: options.views(split) for split in SPLITS}
        self.record_path.write_text(json.dumps(data))

    def poll(self) -> JobStatus:
        running = self.is_running()  # first: a process that ends meanwhile has written everything
        complete = dataset_complete(self.folder)
        failure = self._ended_badly(complete, running)
        if failure is not None:
            return failure
        record = self.record() or {}
        views = record.get("views", {})
        expected = sum(views.values())
        written = sum(len(list((self.folder / split).glob(VIEW_PNG_GLOB))) if (self.folder / split).is_dir() else 0
                      for split in SPLITS)
        if complete and not running:
            return JobStatus("done", 1.0, f"{written} views written")
        if not running and written == 0:
            return JobStatus("idle")
        fraction = min(1.0, written / expected) if expected else 0.0
        return JobStatus("running", fraction, f"{written} of {expected or '?'} views rendered")


class AnimationJob(_Job):
    """A camera animation rendered by the NeRF into ``folder`` (``RUN/animation/CAMERA``), in
    up to two stages, each a process: ``"cycles"``, Cycles' frames by a background Blender
    (``datasets_gen --camera-path ... --cycles``), then ``"nerf"``, the backend's ``render
    --camera-path``. ``poll`` starts the next stage when one has finished; progress is the
    frames on disk, so a reopened .blend follows a job it did not start."""

    STAGE_LABELS = {"cycles": "Cycles", "nerf": "NeRF"}

    def __init__(self, folder: Path) -> None:
        super().__init__(folder)

    def start(self, path_json: Path, frames: int, stages: list[tuple[str, list[str]]],
              env: dict[str, str] | None = None, cycles: bool = False) -> None:
        """Run the ``(kind, command)`` stages one after the other; ``path_json`` is the camera
        path of ``frames`` frames that the "nerf" stage renders (``cycles``: beside Cycles')."""
        self._launch(stages[0][1], env=env)
        self._update(stages=stages, stage=0, path=str(path_json), frames=frames, cycles=cycles, env=env or {},
                     cancelled=False)

    def cancel(self) -> None:
        self._update(cancelled=True)
        super().cancel()

    def _frames_on_disk(self, kind: str, record: dict) -> int:
        folder = Path(record["path"]).parent / CYCLES_FRAMES_DIR if kind == "cycles" else self.folder / ANIMATION_FRAMES_DIR
        return len(list(folder.glob("*.png"))) if folder.is_dir() else 0

    def _launch_next(self, record: dict) -> None:
        stage = record["stage"] + 1
        kept = {key: record[key] for key in ("stages", "path", "frames", "cycles", "env")}
        self._launch(record["stages"][stage][1], env=record.get("env") or None)
        self._update(**kept, stage=stage, cancelled=False)

    def poll(self) -> JobStatus:
        running = self.is_running()
        record = self.record()
        if not record or "stages" not in record:
            return JobStatus("idle")
        stage, stages, total = record["stage"], record["stages"], record["frames"]
        kind, last = stages[stage][0], stage == len(stages) - 1
        done = self._frames_on_disk(kind, record)
        if not running and not last and self.returncode() in (0, None) and not record.get("cancelled") \
                and done >= total:
            self._launch_next(record)
            return JobStatus("running", (stage + 1) / len(stages), f"NeRF: 0 of {total} frames")
        result = self._result(record) if last else None
        finished = result is not None and result.get("video") is not None and (
            not record.get("cycles") or result.get("side_by_side_video") is not None)
        if record.get("cancelled") and not running and not finished:
            return JobStatus("cancelled", 0.0, "cancelled; rendering again keeps the frames already made")
        failure = self._ended_badly(finished, running)
        if failure is not None:
            return failure
        if finished and not running:
            mean = result.get("mean") or {}
            detail = f"{total} frames" + (f", PSNR {mean['psnr']:.2f} dB against Cycles" if mean.get("psnr") else "")
            return JobStatus("done", 1.0, detail, extra={"record": result})
        fraction = (stage + min(1.0, done / total if total else 0.0)) / len(stages)
        return JobStatus("running", fraction, f"{self.STAGE_LABELS[kind]}: {done} of {total} frames")

    def _result(self, record: dict) -> dict | None:
        """The backend's animation.json, if written by this job's render (not an earlier one)."""
        path = self.folder / ANIMATION_RECORD
        try:
            if path.stat().st_mtime < record.get("started", 0.0):
                return None
            return json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            return None


class AssetJob(_Job):
    """``python -m nerf_backend export`` baking the run's asset into ``folder/nerf_asset.glb``
    (``RUN/asset``), watched through the record the export rewrites after each stage."""

    def __init__(self, folder: Path) -> None:
        super().__init__(folder)

    @property
    def asset_path(self) -> Path:
        return self.folder / ASSET_NAME

    def start(self, python: str, backend_root: Path, run: Path, triangles: int, texture_size: int,
              device: str = "auto", cpu_threads: int | None = None) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        command = commands.backend_command(python, commands.export_argv(
            run, self.asset_path, triangles=triangles, texture_size=texture_size, device=device,
            cpu_threads=cpu_threads))
        self._launch(command, env=dict(os.environ, PYTHONPATH=str(backend_root), PYTHONUNBUFFERED="1"))
        self._update(cancelled=False)

    def cancel(self) -> None:
        self._update(cancelled=True)
        super().cancel()

    def _export_record(self, started: float) -> dict | None:
        """The export's record, if this job's export wrote it (not an earlier one)."""
        path = self.asset_path.with_name(ASSET_NAME + ASSET_RECORD_SUFFIX)
        try:
            if path.stat().st_mtime < started:
                return None
            return json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):  # not yet, or being replaced
            return None

    def poll(self) -> JobStatus:
        running = self.is_running()
        job = self.record()
        if not job or "started" not in job:
            return JobStatus("idle")
        record = self._export_record(job["started"]) or {}
        finished = bool(record.get(ASSET_COMPLETE))
        if job.get("cancelled") and not running and not finished:
            return JobStatus("cancelled", 0.0, "cancelled; the asset before it, if any, is unchanged")
        failure = self._ended_badly(finished, running)
        if failure is not None:
            return failure
        if finished and not running:
            detail = (f"{record['triangles']} triangles, {record['texture_size']}² texture, "
                      f"{record['bytes'] / 1e6:.1f} MB")
            return JobStatus("done", 1.0, detail, extra={"asset": str(self.asset_path), "record": record})
        if ASSET_STAGES not in record:  # the export has not written its first record yet
            return JobStatus("running", 0.0, "Export: starting")
        done, stages = record[ASSET_STAGES_DONE], record[ASSET_STAGES]
        return JobStatus("running", done / stages, f"Export: {done} of {stages} stages")


def python_in_venv(venv: Path) -> Path:
    return Path(venv) / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def training_cpu_threads() -> int:
    """The CPU threads a training or baking job gets: all cores but one, as Blender keeps one
    for its UI. torch's threads wait on each other, so one core taken by another program slows
    training about 3x, while training on one core fewer costs about a quarter on 2 cores
    (measured in the README) and less on more."""
    return max(1, (os.cpu_count() or 2) - 1)


def default_base_python() -> str:
    """The interpreter a new backend environment is made from: this one (Blender's own
    Python inside Blender)."""
    return sys.executable
