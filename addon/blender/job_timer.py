"""The jobs the operators start, and the timer that watches them: each job is found by its
folder, its last polled status is what the panel draws, and a timer polls them (and reloads
the live preview) while any runs. Reopening a .blend finds its jobs again."""

from __future__ import annotations

from pathlib import Path

import bpy
from bpy.app.handlers import persistent

from ..core.backend_setup import BackendSetup
from ..core.jobs import AnimationJob, AssetJob, DatasetJob, JobStatus, TrainingJob
from ..core.panel_text import asset_view_warning
from .images import PREVIEW_IMAGE, show_animation, show_image
from .paths import animation_dir, asset_dir, dataset_dir, run_dir
from .scene_import import import_asset

_jobs: dict[str, object] = {}  # folder → job (keeps the Popen that started it)
status: dict[str, JobStatus] = {}  # folder → last polled status, drawn by the panel
_setup: BackendSetup | None = None
_preview_stamp: dict[str, float] = {}  # preview file → the mtime last loaded


def _job(folder, kind):
    """The job of ``kind`` following ``folder``, made on first use."""
    job = _jobs.get(str(folder))
    if not isinstance(job, kind):
        job = _jobs[str(folder)] = kind(folder)
    return job


def training_job(context) -> TrainingJob:
    return _job(run_dir(context), TrainingJob)


def dataset_job(context) -> DatasetJob:
    return _job(dataset_dir(context), DatasetJob)


def animation_job(context) -> AnimationJob:
    """The job rendering the scene camera's animation with the run (``RUN/animation/CAMERA``)."""
    return _job(animation_dir(context), AnimationJob)


def asset_job(context) -> AssetJob:
    """The job baking the run's asset (``RUN/asset``)."""
    return _job(asset_dir(context), AssetJob)


def backend_setup() -> BackendSetup | None:
    """The last Set Up Backend's job, or None."""
    return _setup


def watch_backend_setup(setup: BackendSetup) -> None:
    """Poll ``setup`` (status "backend-setup") instead of the previous one."""
    global _setup
    _setup = setup


def poll_jobs() -> bool:
    """Refresh every known job's status; True while any runs."""
    running = False
    for folder, job in list(_jobs.items()):
        previous = status.get(folder)
        status[folder] = job.poll()
        running = running or status[folder].state == "running"
        if isinstance(job, TrainingJob):
            _refresh_preview(job.preview_path)
        just_done = status[folder].state == "done" and previous is not None and previous.state == "running"
        if isinstance(job, AnimationJob) and just_done:
            _show_animation(job, status[folder])
        if isinstance(job, AssetJob) and just_done:
            _import_asset(status[folder])
    if _setup is not None:
        status["backend-setup"] = _setup.poll()
        running = running or status["backend-setup"].state == "running"
    return running


def _refresh_preview(path: Path) -> None:
    """Reload the live preview only when training wrote a new one: reloading it every poll
    costs a decode and an icon each second."""
    try:
        stamp = path.stat().st_mtime
    except OSError:
        return
    if _preview_stamp.get(str(path)) != stamp or PREVIEW_IMAGE not in bpy.data.images:
        _preview_stamp[str(path)] = stamp
        show_image(PREVIEW_IMAGE, path)


def _show_animation(job: AnimationJob, state: JobStatus) -> None:
    """A finished animation is loaded where the user looks, once (not again on every poll)."""
    context = bpy.context
    try:
        state.extra["shown"] = show_animation(context, state.extra["record"], context.scene.nerf.animation_sequencer)
    except (RuntimeError, OSError, KeyError) as exc:  # a video Blender cannot open: said in the panel
        state.warning = f"The video could not be loaded: {exc}"


def _import_asset(state: JobStatus) -> None:
    """A finished export is imported into the scene, once."""
    try:
        state.extra["imported"] = import_asset(bpy.context, Path(state.extra["asset"])).name
        state.warning = asset_view_warning(bpy.context.scene.view_settings.view_transform)
    except (RuntimeError, OSError, KeyError) as exc:  # a file Blender cannot import: said in the panel
        state.warning = f"The asset could not be imported: {exc}"


def _tick():
    running = poll_jobs()
    # Only what shows the jobs: the sidebars (not the 3D views under them) and Image Editors.
    for window in getattr(bpy.context.window_manager, "windows", []):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.tag_redraw()
            elif area.type == "VIEW_3D":
                for region in area.regions:
                    if region.type == "UI":
                        region.tag_redraw()
    return 1.0 if running else None


def ensure_timer() -> None:
    if not bpy.app.timers.is_registered(_tick):
        bpy.app.timers.register(_tick, first_interval=0.5, persistent=True)


@persistent
def _reattach_on_load(_file) -> None:
    """Reopening a .blend finds its dataset and run again, and a training still running."""
    _jobs.clear()
    status.clear()
    _preview_stamp.clear()
    context = bpy.context
    if getattr(context, "scene", None) is None or not hasattr(context.scene, "nerf"):
        return
    for job in (dataset_job(context), training_job(context), animation_job(context), asset_job(context)):
        status[str(job.folder)] = job.poll()
    if any(s.state == "running" for s in status.values()):
        ensure_timer()


def register() -> None:
    bpy.app.handlers.load_post.append(_reattach_on_load)


def unregister() -> None:
    if _reattach_on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_reattach_on_load)
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
