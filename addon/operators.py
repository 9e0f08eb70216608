"""The panel's buttons. Long work runs in other processes (a background Blender renders the
dataset, the backend's Python trains); a timer polls them through ``jobs`` and redraws.
Blender never waits on them, except where no Blender binary exists to spawn (the ``bpy``
module), where the dataset is rendered in this process."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import subprocess
from pathlib import Path

import bpy
from bpy.app.handlers import persistent

from . import sources, ui_text
from .backend_setup import BackendSetup, check_backend
from .camera_mapping import camera_file
from .jobs import DatasetJob, JobStatus, TrainingJob, default_base_python, python_in_venv

PREVIEW_IMAGE = "NeRF preview"
COMPARISON_IMAGE = "NeRF comparison"
BACKEND_TIMEOUT_S = 3600
WARNINGS_DIALOG_WIDTH = 560  # pixels at UI scale 1: the scene checks' lines, wrapped to it

_jobs: dict[str, object] = {}  # folder → job (keeps the Popen that started it)
status: dict[str, JobStatus] = {}  # folder → last polled status, drawn by the panel
_setup: BackendSetup | None = None
_scene_warnings: list[str] = []  # shown by Generate Dataset's confirmation dialog


# ---------------------------------------------------------------- where things are

def settings(context):
    return context.scene.nerf


def dataset_dir(context) -> Path:
    return Path(bpy.path.abspath(settings(context).dataset_dir)).resolve()


def run_dir(context) -> Path:
    return Path(bpy.path.abspath(settings(context).run_dir)).resolve()


def managed_venv() -> Path:
    """Where Set Up Backend puts the backend's virtual environment (the extension's user folder)."""
    try:
        return Path(bpy.utils.extension_path_user(__package__, path="backend-venv", create=True))
    except (ValueError, AttributeError):  # not installed as an extension (a checkout)
        return Path(bpy.utils.user_resource("SCRIPTS", path="nerf_from_blender_backend", create=True))


def backend_python(context) -> str:
    addon = context.preferences.addons.get(__package__)
    chosen = addon.preferences.python_path if addon is not None else ""
    if chosen:
        return bpy.path.abspath(chosen)
    managed = python_in_venv(managed_venv())
    return str(managed) if managed.is_file() else ""


def training_job(context) -> TrainingJob:
    run = run_dir(context)
    job = _jobs.get(str(run))
    if not isinstance(job, TrainingJob):
        job = _jobs[str(run)] = TrainingJob(run)
    return job


def dataset_job(context) -> DatasetJob:
    out = dataset_dir(context)
    job = _jobs.get(str(out))
    if not isinstance(job, DatasetJob):
        job = _jobs[str(out)] = DatasetJob(out)
    return job


def run_backend(context, *arguments: str) -> subprocess.CompletedProcess:
    """A short backend command (render, compare, report), waited for; its error is raised."""
    python = backend_python(context)
    if not python:
        raise RuntimeError("no backend Python: press Set Up Backend (or set one in the add-on's preferences)")
    result = subprocess.run([python, "-m", "nerf_backend", *arguments], capture_output=True, text=True,
                            timeout=BACKEND_TIMEOUT_S, env={**_environ(), "PYTHONPATH": str(sources.source_root())})
    if result.returncode != 0:
        tail = "\n".join((result.stderr or result.stdout).strip().splitlines()[-6:])
        raise RuntimeError(f"backend {arguments[0]} failed: {tail}")
    return result


def _environ() -> dict:
    import os

    return dict(os.environ)


# ---------------------------------------------------------------- polling

def poll_jobs() -> bool:
    """Refresh every known job's status; True while any runs."""
    running = False
    for folder, job in list(_jobs.items()):
        status[folder] = job.poll()
        running = running or status[folder].state == "running"
        if isinstance(job, TrainingJob):
            _refresh_preview(job.preview_path)
    if _setup is not None:
        status["backend-setup"] = _setup.poll()
        running = running or status["backend-setup"].state == "running"
    return running


_preview_stamp: dict[str, float] = {}  # preview file → the mtime last loaded


def _refresh_preview(path: Path) -> None:
    """Reload the live preview only when training wrote a new one: reloading it every poll
    costs a decode and an icon each second."""
    try:
        stamp = path.stat().st_mtime
    except OSError:
        return
    if _preview_stamp.get(str(path)) != stamp or PREVIEW_IMAGE not in bpy.data.images:
        _preview_stamp[str(path)] = stamp
        _show_image(PREVIEW_IMAGE, path)


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
    for job in (dataset_job(context), training_job(context)):
        status[str(job.folder)] = job.poll()
    if any(s.state == "running" for s in status.values()):
        ensure_timer()


def _show_image(name: str, path: Path):
    """Load (or reload) ``path`` as the image datablock ``name``; returns it."""
    image = bpy.data.images.get(name)
    if image is not None and Path(bpy.path.abspath(image.filepath)).resolve() == Path(path).resolve():
        image.reload()
    else:
        if image is not None:
            bpy.data.images.remove(image)
        image = bpy.data.images.load(str(path), check_existing=False)
        image.name = name
    return image


def show_in_image_editor(context, image) -> str:
    """Show ``image`` where the user looks: in an open Image Editor, else in a new window
    turned into one. Returns where ("" without a window: the ``bpy`` module, ``blender -b``)."""
    if bpy.app.background:  # no screen to show it on (the bpy module, blender -b)
        return ""
    windows = list(getattr(context.window_manager, "windows", []))
    for window in windows:
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image
                _fit_when_drawn(window, area)
                return "an open Image Editor"
    window = context.window or (windows[0] if windows else None)
    if window is None:
        return ""
    area = context.area or window.screen.areas[0]
    with context.temp_override(window=window, area=area):
        bpy.ops.wm.window_new()
    new_window = context.window_manager.windows[-1]
    editor = max(new_window.screen.areas, key=lambda a: a.width * a.height)
    editor.type = "IMAGE_EDITOR"
    editor.spaces.active.image = image
    _fit_when_drawn(new_window, editor)
    return "a new Image Editor window"


def _fit_when_drawn(window, area) -> None:
    """Zoom the editor so the image fills it (a 100-pixel render is a speck at 1:1); once the
    area has been drawn, since a new window's regions have no size before."""
    def fit():
        if window not in bpy.context.window_manager.windows[:]:
            return None  # closed meanwhile: nothing to fit
        region = next((r for r in area.regions if r.type == "WINDOW"), None)
        if region is not None:
            with bpy.context.temp_override(window=window, area=area, region=region):
                bpy.ops.image.view_all(fit_view=True)
        return None
    area.tag_redraw()
    bpy.app.timers.register(fit, first_interval=0.3)


# ---------------------------------------------------------------- dataset

def _dataset_arguments(context) -> list[str]:
    s = settings(context)
    arguments = ["--train-views", str(s.train_views), "--val-views", str(s.val_views), "--test-views", str(s.test_views),
                 "--resolution", str(s.resolution), "--samples", str(s.samples), "--device", s.render_device,
                 "--seed", str(s.seed), "--depth-normals", s.depth_normals]
    return arguments + (["--sphere"] if s.sphere else [])


def _dataset_complete(out: Path) -> bool:
    return all((out / f"transforms_{split}.json").is_file() for split in DatasetJob.SPLITS)


def scene_warnings(context) -> list[str]:
    """What the generator's scene checks say about the open scene (missing files, settings
    it will replace for the render), without rendering anything."""
    generator = sources.datasets_gen("generator")
    profile = generator.generate_dataset("", scene=context.scene, check_only=True, progress=False)
    checks = profile.get("checks", {})
    return [str(line) for line in list(checks.get("errors", [])) + list(checks.get("notes", []))]


class NERF_OT_generate_dataset(bpy.types.Operator):
    """Render the NeRF dataset of this scene with Cycles (in a background Blender)"""

    bl_idname = "nerf.generate_dataset"
    bl_label = "Generate Dataset"

    def invoke(self, context, event):
        global _scene_warnings
        try:
            _scene_warnings = scene_warnings(context)
        except Exception as exc:  # the generator's own errors name the problem
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if _scene_warnings:
            return context.window_manager.invoke_props_dialog(self, width=WARNINGS_DIALOG_WIDTH)
        return self.execute(context)

    def draw(self, context):
        self.layout.label(text="The scene checks found:")
        for line in _scene_warnings:
            # Less the dialog's margins and the icon.
            ui_text.draw_text(self.layout, context, str(line), icon="ERROR", width_px=WARNINGS_DIALOG_WIDTH - 50)

    def execute(self, context):
        out = dataset_dir(context)
        if _dataset_complete(out):
            self.report({"ERROR"}, f"{out} already holds a complete dataset; choose another folder or remove it")
            return {"CANCELLED"}
        arguments = _dataset_arguments(context) + (["--resume"] if out.exists() and any(out.iterdir()) else [])
        if bpy.app.binary_path:
            job = dataset_job(context)
            if job.is_running():
                self.report({"ERROR"}, "this dataset is already being rendered")
                return {"CANCELLED"}
            copy = out.with_name(out.name + ".scene.blend")  # the scene as it is now, unsaved edits included
            copy.parent.mkdir(parents=True, exist_ok=True)
            bpy.ops.wm.save_as_mainfile(filepath=str(copy), copy=True, check_existing=False)
            job.start(bpy.app.binary_path, copy, sources.source_root(), arguments)
            ensure_timer()
            self.report({"INFO"}, f"rendering the dataset into {out} in the background")
            return {"FINISHED"}
        return self._render_here(context, out, arguments)

    def _render_here(self, context, out: Path, arguments: list[str]):
        """No Blender binary to spawn (the bpy module): render in this process."""
        s = settings(context)
        generator = sources.datasets_gen("generator")
        window_manager = context.window_manager
        window_manager.progress_begin(0, 1)
        try:
            generator.generate_dataset(
                str(out), scene=context.scene, train_views=s.train_views, val_views=s.val_views,
                test_views=s.test_views, width=s.resolution, height=s.resolution, samples=s.samples, seed=s.seed,
                full_sphere=s.sphere, device=s.render_device, depth_normals=s.depth_normals,
                resume="--resume" in arguments, progress=False)
        except Exception as exc:  # the generator's errors name the file and the problem
            self.report({"ERROR"}, f"dataset generation failed: {exc}")
            return {"CANCELLED"}
        finally:
            window_manager.progress_end()
        status[str(out)] = dataset_job(context).poll()
        self.report({"INFO"}, f"dataset written to {out}")
        return {"FINISHED"}


# ---------------------------------------------------------------- training

def training_cpu_threads() -> int:
    """All cores but one: Blender keeps one for its UI. torch's threads wait on each other, so
    one core taken by another program slows training about 3x, while training on one core
    fewer costs about a quarter on 2 cores (measured in the README) and less on more."""
    return max(1, (os.cpu_count() or 2) - 1)


class NERF_OT_train(bpy.types.Operator):
    """Train a NeRF on the dataset in the backend's Python; returns at once"""

    bl_idname = "nerf.train"
    bl_label = "Train"

    resume: bpy.props.BoolProperty(default=False, options={"SKIP_SAVE"})

    def execute(self, context):
        s = settings(context)
        python = backend_python(context)
        ok, message = check_backend(python)
        if not ok:
            self.report({"ERROR"}, message)
            return {"CANCELLED"}
        job = training_job(context)
        if job.is_running():
            self.report({"ERROR"}, "this run is already training")
            return {"CANCELLED"}
        if not self.resume and job.run.exists() and any(job.run.iterdir()):
            self.report({"ERROR"}, f"{job.run} already holds a run: press Resume, or choose another run folder")
            return {"CANCELLED"}
        by_time = s.budget_kind == "TIME"
        job.start(python, sources.source_root(), dataset_dir(context), s.preset,
                  iterations=None if by_time else s.budget_iterations, max_seconds=s.budget_seconds if by_time else None,
                  device=s.train_device, resume=self.resume, cpu_threads=training_cpu_threads())
        ensure_timer()
        return {"FINISHED"}


class NERF_OT_cancel_training(bpy.types.Operator):
    """Stop training after it saves a checkpoint (Resume continues it)"""

    bl_idname = "nerf.cancel_training"
    bl_label = "Cancel"

    def execute(self, context):
        training_job(context).cancel()
        return {"FINISHED"}


# ---------------------------------------------------------------- results

def _dataset_camera_settings(context) -> tuple[dict, dict]:
    """``world_to_nerf`` and image size of the dataset (its test split's JSON)."""
    path = dataset_dir(context) / "transforms_test.json"
    if not path.is_file():
        raise RuntimeError(f"{path}: no dataset yet; generate one first")
    data = json.loads(path.read_text())
    return data.get("world_to_nerf", {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}), {"w": data["w"], "h": data["h"]}


def _active_camera_intrinsics(context, width: int, height: int) -> dict:
    camera = context.scene.camera
    if camera is None or camera.type != "CAMERA" or camera.data.type != "PERSP":
        raise RuntimeError("the scene needs an active perspective camera")
    render = context.scene.render
    intrinsics = sources.datasets_gen("intrinsics").camera_intrinsics(
        lens_mm=camera.data.lens, sensor_width_mm=camera.data.sensor_width, sensor_height_mm=camera.data.sensor_height,
        sensor_fit=camera.data.sensor_fit, resolution_x=width, resolution_y=height,
        pixel_aspect_x=render.pixel_aspect_x, pixel_aspect_y=render.pixel_aspect_y,
        shift_x=camera.data.shift_x, shift_y=camera.data.shift_y)
    return intrinsics.as_dict()


def render_active_camera_nerf(context) -> Path:
    """The NeRF's render of the scene's active camera, at the dataset's resolution."""
    world_to_nerf, size = _dataset_camera_settings(context)
    intrinsics = _active_camera_intrinsics(context, size["w"], size["h"])
    out = run_dir(context) / "active_camera"
    out.mkdir(parents=True, exist_ok=True)
    cameras = out / "camera.json"
    matrix = [list(row) for row in context.scene.camera.matrix_world]
    cameras.write_text(json.dumps(camera_file(matrix, world_to_nerf, intrinsics, "nerf")))
    run_backend(context, "render", str(run_dir(context)), "--cameras", str(cameras), "--out", str(out))
    return out / "nerf.png"


def _reporting_backend_errors(execute):
    """An operator's ``execute`` whose failure (the backend's own one-line error, a timeout,
    the generator's error, a file that cannot be written) is shown as an error report and
    cancels, instead of a traceback."""

    @functools.wraps(execute)
    def wrapped(self, context):
        try:
            return execute(self, context)
        except (RuntimeError, OSError, subprocess.TimeoutExpired, sources.datasets_gen("options").DatasetGenError) as exc:
            self.report({"ERROR"}, str(exc))  # the generator's errors too: Compare renders through it
            return {"CANCELLED"}

    return wrapped


class NERF_OT_render_test_views(bpy.types.Operator):
    """Render the dataset's test views with the trained NeRF and load them as images"""

    bl_idname = "nerf.render_test_views"
    bl_label = "Render Test Views"

    @_reporting_backend_errors
    def execute(self, context):
        run_backend(context, "render", str(run_dir(context)), "--split", "test", "--no-progress")
        renders = sorted((run_dir(context) / "renders" / "test").glob("r_*.png"), key=lambda p: int(p.stem[2:]))
        images = [_show_image(f"NeRF test {path.stem}", path) for path in renders]
        where = show_in_image_editor(context, images[0]) if images else ""
        self.report({"INFO"}, f"loaded {len(renders)} test renders as images 'NeRF test r_N'"
                    + (f", the first shown in {where}" if where else ""))
        return {"FINISHED"}


class NERF_OT_render_active_camera(bpy.types.Operator):
    """Render the view from the active camera with the trained NeRF"""

    bl_idname = "nerf.render_active_camera"
    bl_label = "Render Active Camera"

    @_reporting_backend_errors
    def execute(self, context):
        image = _show_image("NeRF active camera", render_active_camera_nerf(context))
        show_in_image_editor(context, image)
        return {"FINISHED"}


def render_active_camera_cycles(context, path: Path, width: int, height: int) -> Path:
    """Cycles' render of the active camera as the dataset's views were rendered, by the
    generator's own code: its protocol settings (no denoiser, transparent film, Standard view,
    the dataset's samples and seed) at the dataset's size; the scene's settings are restored
    afterwards."""
    blender_render = sources.datasets_gen("blender_render")
    generator = json.loads((dataset_dir(context) / "transforms_test.json").read_text()).get("generator", {})
    scene = context.scene
    camera = dataclasses.replace(blender_render.read_scene_camera(scene), resolution_x=width, resolution_y=height,
                                 resolution_percentage=100)
    journal = sources.datasets_gen("scene_state").SettingsJournal()
    try:
        blender_render.configure_render(
            scene, context.view_layer, journal, camera=camera, samples=int(generator.get("samples", 128)),
            seed=int(generator.get("cycles_seed", 0)), device=settings(context).render_device,
            color_management=generator.get("color_management", "standard"), passes=False)
        blender_render.render_view(scene, context.view_layer, {"png": str(path)})
    finally:
        journal.restore()
    return path


class NERF_OT_compare(bpy.types.Operator):
    """Render the active camera with Cycles and with the NeRF; show both and their difference, with metrics"""

    bl_idname = "nerf.compare"
    bl_label = "Compare with Cycles"

    @_reporting_backend_errors
    def execute(self, context):
        _, size = _dataset_camera_settings(context)
        nerf = render_active_camera_nerf(context)
        cycles = render_active_camera_cycles(context, nerf.with_name("cycles.png"), size["w"], size["h"])
        run_backend(context, "compare", "--reference", str(cycles), "--render", str(nerf), "--out", str(nerf.parent))
        result = json.loads((nerf.parent / "compare.json").read_text())
        s = settings(context)
        s.compare_psnr, s.compare_ssim = result["psnr"], result["ssim"]
        s.compare_lpips = f"{result['lpips']:.4f}" if result["lpips"] is not None else "unavailable"
        for name, path in (("Cycles active camera", cycles), ("NeRF active camera", nerf),
                           ("NeRF difference", nerf.parent / "difference.png")):
            _show_image(name, path)
        # Cycles, the NeRF and their difference side by side, with the numbers.
        show_in_image_editor(context, _show_image(COMPARISON_IMAGE, nerf.parent / "side_by_side.png"))
        self.report({"INFO"}, f"PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}, LPIPS {s.compare_lpips}")
        return {"FINISHED"}


class NERF_OT_open_report(bpy.types.Operator):
    """Write the HTML comparison report of the run and open it in the web browser"""

    bl_idname = "nerf.open_report"
    bl_label = "Open Report"

    @_reporting_backend_errors
    def execute(self, context):
        run_backend(context, "report", str(run_dir(context)))
        page = run_dir(context) / "report" / "index.html"
        bpy.ops.wm.url_open(url=page.as_uri())
        return {"FINISHED"}


# ---------------------------------------------------------------- backend

class NERF_OT_setup_backend(bpy.types.Operator):
    """Create a Python environment with the backend's packages (torch...) for training"""

    bl_idname = "nerf.setup_backend"
    bl_label = "Set Up Backend"

    def execute(self, context):
        global _setup
        if _setup is not None and _setup.poll().state == "running":
            self.report({"ERROR"}, "the backend is already being set up")
            return {"CANCELLED"}
        _setup = BackendSetup(managed_venv(), default_base_python(), sources.backend_requirements())
        try:
            _setup.start()
        except (OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        ensure_timer()
        return {"FINISHED"}


CLASSES = (NERF_OT_generate_dataset, NERF_OT_train, NERF_OT_cancel_training, NERF_OT_render_test_views,
           NERF_OT_render_active_camera, NERF_OT_compare, NERF_OT_open_report, NERF_OT_setup_backend)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.app.handlers.load_post.append(_reattach_on_load)


def unregister() -> None:
    if _reattach_on_load in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_reattach_on_load)
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
