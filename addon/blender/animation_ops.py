"""Render Camera Animation (the NeRF along the scene camera's animation, beside Cycles' frames),
its Cancel, Import NeRF Mesh, and Import NeRF Asset (a job: the backend bakes the asset, the
timer imports it when done) with its Cancel. The animation runs in other processes like training (a
background Blender renders Cycles' frames, then the backend renders the NeRF's); when it is
done the video is loaded into an Image Editor and, if asked, into the Video Sequencer."""

from __future__ import annotations

import os
from pathlib import Path

import bpy

from datasets_gen import camera_path_export
from datasets_gen.core.options import options_from_keywords, options_to_argv
from nerf_contract import commands
from nerf_contract.dataset_layout import CAMERA_PATH_NAME
from nerf_contract.run_layout import CHECKPOINT_NAME

from ..core import sources
from ..core.backend_setup import check_backend
from ..core.jobs import training_cpu_threads
from .job_timer import animation_job, asset_job, ensure_timer
from .paths import backend_python, dataset_dir, run_dir, settings
from .results_ops import reporting_backend_errors, run_backend
from .scene_import import import_mesh


def trained_run_backend(context) -> str:
    """The backend's Python, once it is set up and the run has a checkpoint (RuntimeError, said
    to the user, otherwise)."""
    python = backend_python(context)
    ok, message = check_backend(python)
    if not ok:
        raise RuntimeError(message)
    if not (run_dir(context) / CHECKPOINT_NAME).is_file():
        raise RuntimeError(f"{run_dir(context)}: no trained run yet; train first")
    return python


def scene_frames(context) -> range:
    scene = context.scene
    return range(scene.frame_start, scene.frame_end + 1, max(1, settings(context).animation_step))


class NERF_OT_render_animation(bpy.types.Operator):
    """Render the trained NeRF along the scene camera's animation (the scene's frame range) as a
    video, beside Cycles' frames if asked; runs in the background"""

    bl_idname = "nerf.render_animation"
    bl_label = "Render Camera Animation"

    @reporting_backend_errors
    def execute(self, context):
        s, scene = settings(context), context.scene
        python = trained_run_backend(context)
        if scene.camera is None or scene.camera.type != "CAMERA":
            raise RuntimeError("the scene needs an active camera: its animation is what is rendered")
        job = animation_job(context)
        if job.is_running():
            raise RuntimeError("this animation is already being rendered")
        frames = scene_frames(context)
        dataset = dataset_dir(context)
        path_json = Path(camera_path_export.path_folder(str(dataset), scene.camera.name)) / CAMERA_PATH_NAME
        frame_text = f"{frames.start}:{frames.stop - 1}:{frames.step}"
        stages = []
        if s.animation_cycles and bpy.app.binary_path:
            copy = job.folder.with_name(job.folder.name + ".scene.blend")  # the scene as it is now
            copy.parent.mkdir(parents=True, exist_ok=True)
            bpy.ops.wm.save_as_mainfile(filepath=str(copy), copy=True, check_existing=False)
            # overwrite: a changed animation replaces its stale Cycles frames; unchanged ones are kept.
            options = options_from_keywords(out_dir=str(dataset), open_scene=True, device=s.render_device,
                                            overwrite=True)
            argv = [*options_to_argv(options), *commands.camera_path_argv(scene.camera.name, frame_text, with_cycles=True),
                    commands.GeneratorFlag.NO_PROGRESS]
            stages.append(("cycles", commands.blender_script_command(bpy.app.binary_path, copy,
                                                                     sources.generator_script(), argv)))
        else:  # the path alone is quick; without a Blender binary (the bpy module) Cycles renders here
            self._export_here(context, dataset, frames, s.animation_cycles)
        render = commands.render_camera_path_argv(run_dir(context), path_json, job.folder, device=s.train_device,
                                                  cycles=s.animation_cycles)
        stages.append(("nerf", commands.backend_command(python, render)))
        env = dict(os.environ, PYTHONPATH=str(sources.backend_root()), PYTHONUNBUFFERED="1")
        job.start(path_json, len(frames), stages, env=env, cycles=s.animation_cycles)
        ensure_timer()
        self.report({"INFO"}, f"rendering {len(frames)} frames of {scene.camera.name!r} into {job.folder}")
        return {"FINISHED"}

    @staticmethod
    def _export_here(context, dataset: Path, frames: range, cycles: bool) -> None:
        window_manager = context.window_manager
        window_manager.progress_begin(0, 1)
        try:
            camera_path_export.export_camera_path(str(dataset), context.scene.camera.name, frames, scene=context.scene,
                                      cycles=cycles, overwrite=True, device=settings(context).render_device,
                                      progress=False)
        finally:
            window_manager.progress_end()


class NERF_OT_cancel_animation(bpy.types.Operator):
    """Stop rendering the animation (rendering it again keeps the frames already made)"""

    bl_idname = "nerf.cancel_animation"
    bl_label = "Cancel"

    def execute(self, context):
        animation_job(context).cancel()
        return {"FINISHED"}


class NERF_OT_import_mesh(bpy.types.Operator):
    """Extract the trained NeRF's surface (marching cubes) and add it to the scene, over the
    original, with its colours"""

    bl_idname = "nerf.import_mesh"
    bl_label = "Import NeRF Mesh"

    @reporting_backend_errors
    def execute(self, context):
        s = settings(context)
        run = run_dir(context)
        out = run / "mesh" / f"nerf_mesh_{s.mesh_resolution}.ply"
        out.parent.mkdir(parents=True, exist_ok=True)
        run_backend(context, commands.mesh_argv(run, out, resolution=s.mesh_resolution, device=s.train_device,
                                                overwrite=True))
        obj = import_mesh(context, out)
        self.report({"INFO"}, f"imported {obj.name}: {len(obj.data.vertices)} vertices from {out}")
        return {"FINISHED"}


class NERF_OT_import_asset(bpy.types.Operator):
    """Bake the trained NeRF into a textured asset (its surface decimated to the triangle budget,
    its colour in a texture) and add it to the scene over the original; runs in the background"""

    bl_idname = "nerf.import_asset"
    bl_label = "Import NeRF Asset"

    @reporting_backend_errors
    def execute(self, context):
        s = settings(context)
        python = trained_run_backend(context)
        job = asset_job(context)
        if job.is_running():
            raise RuntimeError("the asset is already being baked")
        job.start(python, sources.backend_root(), run_dir(context), s.asset_triangles, int(s.asset_texture_size),
                  device=s.train_device, cpu_threads=training_cpu_threads())
        ensure_timer()
        self.report({"INFO"}, f"baking the asset into {job.asset_path}")
        return {"FINISHED"}


class NERF_OT_cancel_asset(bpy.types.Operator):
    """Stop baking the asset (the one baked before, if any, stays)"""

    bl_idname = "nerf.cancel_asset"
    bl_label = "Cancel"

    def execute(self, context):
        asset_job(context).cancel()
        return {"FINISHED"}


CLASSES = (NERF_OT_render_animation, NERF_OT_cancel_animation, NERF_OT_import_mesh, NERF_OT_import_asset,
           NERF_OT_cancel_asset)
