"""Generate Dataset: the open scene's dataset, rendered by the generator (``datasets_gen``)
with the panel's settings, in a background Blender; in this process where no Blender binary
exists to spawn (the ``bpy`` module)."""

from __future__ import annotations

from pathlib import Path

import bpy

from datasets_gen import generator
from datasets_gen.core.options import options_from_keywords

from ..core import sources
from ..core.jobs import dataset_complete
from . import ui_text
from .job_timer import dataset_job, ensure_timer, status
from .paths import dataset_dir, settings

WARNINGS_DIALOG_WIDTH = 560  # pixels at UI scale 1: the scene checks' lines, wrapped to it

_scene_warnings: list[str] = []  # shown by Generate Dataset's confirmation dialog


def dataset_options(context, out: Path):
    """The panel's settings as the generator's options (``GeneratorOptions``) for the open
    scene, rendered into ``out``: resumed when ``out`` already holds something."""
    s = settings(context)
    return options_from_keywords(
        out_dir=str(out), open_scene=True, train_views=s.train_views, val_views=s.val_views, test_views=s.test_views,
        width=s.resolution, height=s.resolution, samples=s.samples, device=s.render_device, seed=s.seed,
        depth_normals=s.depth_normals, full_sphere=s.sphere, formats=tuple(sorted(s.dataset_formats)),
        resume=out.exists() and any(out.iterdir()))


def scene_warnings(context) -> list[str]:
    """What the generator's scene checks say about the open scene (missing files, settings
    it will replace for the render), without rendering anything."""
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
        if dataset_complete(out):
            self.report({"ERROR"}, f"{out} already holds a complete dataset; choose another folder or remove it")
            return {"CANCELLED"}
        options = dataset_options(context, out)
        if bpy.app.binary_path:
            job = dataset_job(context)
            if job.is_running():
                self.report({"ERROR"}, "this dataset is already being rendered")
                return {"CANCELLED"}
            copy = out.with_name(out.name + ".scene.blend")  # the scene as it is now, unsaved edits included
            copy.parent.mkdir(parents=True, exist_ok=True)
            bpy.ops.wm.save_as_mainfile(filepath=str(copy), copy=True, check_existing=False)
            # The background Blender opens the copy: the open scene needs no flag.
            job.start(bpy.app.binary_path, copy, sources.generator_script(), options)
            ensure_timer()
            self.report({"INFO"}, f"rendering the dataset into {out} in the background")
            return {"FINISHED"}
        return self._render_here(context, options)

    def _render_here(self, context, options):
        """No Blender binary to spawn (the bpy module): render in this process."""
        window_manager = context.window_manager
        window_manager.progress_begin(0, 1)
        try:
            generator.run(options, progress=False, scene=context.scene)
        except Exception as exc:  # the generator's errors name the file and the problem
            self.report({"ERROR"}, f"dataset generation failed: {exc}")
            return {"CANCELLED"}
        finally:
            window_manager.progress_end()
        status[options.out_dir] = dataset_job(context).poll()
        self.report({"INFO"}, f"dataset written to {options.out_dir}")
        return {"FINISHED"}


CLASSES = (NERF_OT_generate_dataset,)
