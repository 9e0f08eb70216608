"""What a trained run shows: its test views and the active camera rendered by the NeRF and
loaded as images, Compare with Cycles (the active camera rendered by both, with metrics), and
the HTML report. Each asks the backend's Python for a short command and waits for it."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import subprocess
from pathlib import Path

import bpy

from datasets_gen.blender import render as blender_render
from datasets_gen.blender.scene_state import SettingsJournal
from datasets_gen.core.camera_path import camera_to_nerf
from datasets_gen.core.intrinsics import camera_intrinsics
from datasets_gen.core.options import DatasetGenError
from nerf_contract import commands
from nerf_contract.dataset_layout import VIEW_PNG_GLOB, transforms_name
from nerf_contract.run_layout import (
    COMPARE_NAME,
    DIFFERENCE_NAME,
    RENDERS_DIR,
    REPORT_DIR,
    REPORT_INDEX,
    SIDE_BY_SIDE_NAME,
)

from ..core import sources
from .images import COMPARISON_IMAGE, show_image, show_in_image_editor
from .paths import backend_python, dataset_dir, run_dir, settings

BACKEND_TIMEOUT_S = 3600


def run_backend(context, argv: list[str]) -> subprocess.CompletedProcess:
    """A short backend command (``nerf_contract.commands``' render, compare, report...), waited
    for; its error is raised."""
    python = backend_python(context)
    if not python:
        raise RuntimeError("no backend Python: press Set Up Backend (or set one in the add-on's preferences)")
    result = subprocess.run(commands.backend_command(python, argv), capture_output=True, text=True,
                            timeout=BACKEND_TIMEOUT_S, env={**os.environ, "PYTHONPATH": str(sources.backend_root())})
    if result.returncode != 0:
        tail = "\n".join((result.stderr or result.stdout).strip().splitlines()[-6:])
        raise RuntimeError(f"backend {argv[0]} failed: {tail}")
    return result


def reporting_backend_errors(execute):
    """An operator's ``execute`` whose failure (the backend's own one-line error, a timeout,
    the generator's error, a file that cannot be written) is shown as an error report and
    cancels, instead of a traceback."""

    @functools.wraps(execute)
    def wrapped(self, context):
        try:
            return execute(self, context)
        except (RuntimeError, OSError, subprocess.TimeoutExpired, DatasetGenError) as exc:
            self.report({"ERROR"}, str(exc))  # the generator's errors too: Compare renders through it
            return {"CANCELLED"}

    return wrapped


def _dataset_camera_settings(context) -> tuple[dict, dict]:
    """``world_to_nerf`` and image size of the dataset (its test split's JSON)."""
    path = dataset_dir(context) / transforms_name("test")
    if not path.is_file():
        raise RuntimeError(f"{path}: no dataset yet; generate one first")
    data = json.loads(path.read_text())
    return data.get("world_to_nerf", {"scale": 1.0, "translation": [0.0, 0.0, 0.0]}), {"w": data["w"], "h": data["h"]}


def _active_camera_intrinsics(context, width: int, height: int) -> dict:
    camera = context.scene.camera
    if camera is None or camera.type != "CAMERA" or camera.data.type != "PERSP":
        raise RuntimeError("the scene needs an active perspective camera")
    render = context.scene.render
    intrinsics = camera_intrinsics(
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
    pose = camera_to_nerf(matrix, world_to_nerf)
    keys = ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_angle_x")
    cameras.write_text(json.dumps({**{k: intrinsics[k] for k in keys},
                                   "frames": [{"file_path": "./nerf", "transform_matrix": pose}]}))
    run_backend(context, commands.render_cameras_argv(run_dir(context), cameras, out))
    return out / "nerf.png"


def render_active_camera_cycles(context, path: Path, width: int, height: int) -> Path:
    """Cycles' render of the active camera as the dataset's views were rendered, by the
    generator's own code: its protocol settings (no denoiser, transparent film, Standard view,
    the dataset's samples and seed) at the dataset's size; the scene's settings are restored
    afterwards."""
    generator = json.loads((dataset_dir(context) / transforms_name("test")).read_text()).get("generator", {})
    scene = context.scene
    camera = dataclasses.replace(blender_render.read_scene_camera(scene), resolution_x=width, resolution_y=height,
                                 resolution_percentage=100)
    journal = SettingsJournal()
    try:
        blender_render.configure_render(
            scene, context.view_layer, journal, camera=camera, samples=int(generator.get("samples", 128)),
            seed=int(generator.get("cycles_seed", 0)), device=settings(context).render_device,
            color_management=generator.get("color_management", "standard"), passes=False)
        blender_render.render_view(scene, context.view_layer, {"png": str(path)})
    finally:
        journal.restore()
    return path


class NERF_OT_render_test_views(bpy.types.Operator):
    """Render the dataset's test views with the trained NeRF and load them as images"""

    bl_idname = "nerf.render_test_views"
    bl_label = "Render Test Views"

    @reporting_backend_errors
    def execute(self, context):
        run_backend(context, commands.render_split_argv(run_dir(context), "test"))
        renders = sorted((run_dir(context) / RENDERS_DIR / "test").glob(VIEW_PNG_GLOB), key=lambda p: int(p.stem[2:]))
        images = [show_image(f"NeRF test {path.stem}", path) for path in renders]
        where = show_in_image_editor(context, images[0]) if images else ""
        self.report({"INFO"}, f"loaded {len(renders)} test renders as images 'NeRF test r_N'"
                    + (f", the first shown in {where}" if where else ""))
        return {"FINISHED"}


class NERF_OT_render_active_camera(bpy.types.Operator):
    """Render the view from the active camera with the trained NeRF"""

    bl_idname = "nerf.render_active_camera"
    bl_label = "Render Active Camera"

    @reporting_backend_errors
    def execute(self, context):
        image = show_image("NeRF active camera", render_active_camera_nerf(context))
        show_in_image_editor(context, image)
        return {"FINISHED"}


class NERF_OT_compare(bpy.types.Operator):
    """Render the active camera with Cycles and with the NeRF; show both and their difference, with metrics"""

    bl_idname = "nerf.compare"
    bl_label = "Compare with Cycles"

    @reporting_backend_errors
    def execute(self, context):
        _, size = _dataset_camera_settings(context)
        nerf = render_active_camera_nerf(context)
        cycles = render_active_camera_cycles(context, nerf.with_name("cycles.png"), size["w"], size["h"])
        run_backend(context, commands.compare_argv(cycles, nerf, nerf.parent))
        result = json.loads((nerf.parent / COMPARE_NAME).read_text())
        s = settings(context)
        rows = result["metrics"]  # each metric as the backend formats it: key, label, value, text
        s.compare_metrics = json.dumps(rows)
        for name, path in (("Cycles active camera", cycles), ("NeRF active camera", nerf),
                           ("NeRF difference", nerf.parent / DIFFERENCE_NAME)):
            show_image(name, path)
        # Cycles, the NeRF and their difference side by side, with the numbers.
        show_in_image_editor(context, show_image(COMPARISON_IMAGE, nerf.parent / SIDE_BY_SIDE_NAME))
        self.report({"INFO"}, ", ".join(f"{row['label']} {row['text']}" for row in rows))
        return {"FINISHED"}


class NERF_OT_open_report(bpy.types.Operator):
    """Write the HTML comparison report of the run and open it in the web browser"""

    bl_idname = "nerf.open_report"
    bl_label = "Open Report"

    @reporting_backend_errors
    def execute(self, context):
        run_backend(context, commands.report_argv(run_dir(context)))
        page = run_dir(context) / REPORT_DIR / REPORT_INDEX
        bpy.ops.wm.url_open(url=page.as_uri())
        return {"FINISHED"}


CLASSES = (NERF_OT_render_test_views, NERF_OT_render_active_camera, NERF_OT_compare, NERF_OT_open_report)
