"""View3D › Sidebar › NeRF: dataset, training, results, each with sub-panels. Drawing only;
the buttons are in ``operators``, the job state comes from ``job_timer``'s last poll and the
wording from ``core.panel_text``.

Blender's conventions: property split (label left, field right) so labels get a column of
their own at any sidebar width, title-case labels, settings that are not needed every time
in sub-panels."""

from __future__ import annotations

import json
import time

import bpy

from ..core.panel_text import live_view_rate, progress_texts
from . import render_composite, viewport_overlay
from .images import COMPARISON_IMAGE, PREVIEW_IMAGE
from .job_timer import status
from .paths import animation_dir, asset_dir, backend_python, dataset_dir, run_dir, torch_build
from .ui_text import draw_text as _text
from .ui_text import first_fitting


def _draw_status(layout, context, state, idle_text: str) -> None:
    if state is None or state.state == "idle":
        layout.label(text=idle_text, icon="INFO")
        return
    if state.state == "running":
        candidates = progress_texts(state.detail, state.seconds_left, state.iteration, state.psnr)
        layout.progress(factor=state.fraction, type="BAR", text=first_fitting(context, candidates))
    elif state.state == "failed":
        box = layout.box()
        box.alert = True
        box.label(text="Failed", icon="ERROR")
        _text(box, context, state.error)
    else:
        icon = "CHECKMARK" if state.state == "done" else "PAUSE"
        _text(layout, context, f"{state.state.capitalize()}: {state.detail}", icon)
    if state.warning and state.state != "failed":
        _text(layout.box(), context, state.warning, icon="ERROR", limit=6)


def _draw_job(layout, context, folder, start: tuple[str, str], cancel: str, idle_text: str) -> None:
    """A background job's button (``start``: operator and icon; ``cancel`` while it runs) and its status."""
    state = status.get(str(folder))
    if state is not None and state.state == "running":
        layout.operator(cancel, icon="CANCEL")
    else:
        layout.operator(start[0], icon=start[1])
    _draw_status(layout, context, state, idle_text)


def _value_row(layout, label: str, value: str) -> None:
    """A read-only value in the property-split layout: label right-aligned left, value right."""
    split = layout.split(factor=0.4)
    left = split.row()
    left.alignment = "RIGHT"
    left.label(text=label)
    split.label(text=value)


def _split(layout):
    layout.use_property_split = True
    layout.use_property_decorate = False  # no keyframe dots: these are not animatable settings
    return layout


class _NerfPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeRF"


class NERF_PT_dataset(_NerfPanel, bpy.types.Panel):
    bl_label = "Dataset"

    def draw(self, context):
        s, layout = context.scene.nerf, _split(self.layout)
        layout.prop(s, "dataset_dir")
        col = layout.column(align=True)
        col.prop(s, "train_views")
        col.prop(s, "val_views")
        col.prop(s, "test_views")
        layout.prop(s, "resolution")
        layout.operator("nerf.generate_dataset", icon="RENDER_STILL")
        _draw_status(layout, context, status.get(str(dataset_dir(context))), "No dataset rendering")


class NERF_PT_dataset_rendering(_NerfPanel, bpy.types.Panel):
    bl_label = "Rendering"
    bl_parent_id = "NERF_PT_dataset"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        s, layout = context.scene.nerf, _split(self.layout)
        layout.prop(s, "samples")
        layout.prop(s, "render_device")
        layout.prop(s, "depth_normals")
        layout.prop(s, "sphere")
        layout.prop(s, "seed")
        layout.prop(s, "dataset_formats")


class NERF_PT_training(_NerfPanel, bpy.types.Panel):
    bl_label = "Training"

    def draw(self, context):
        s, layout = context.scene.nerf, _split(self.layout)
        layout.prop(s, "run_dir")
        layout.prop(s, "preset")
        layout.row().prop(s, "budget_kind", expand=True)
        layout.prop(s, "budget_seconds" if s.budget_kind == "TIME" else "budget_iterations")
        layout.prop(s, "train_device")
        state = status.get(str(run_dir(context)))
        row = layout.row(align=True)
        if state is not None and state.state == "running":
            row.operator("nerf.cancel_training", icon="CANCEL")
        else:
            row.operator("nerf.train", icon="PLAY").resume = False
            row.operator("nerf.train", text="Resume", icon="FILE_REFRESH").resume = True
        _draw_status(layout, context, state, "Not training")
        setup = status.get("backend-setup")
        if setup is not None:
            _draw_status(layout, context, setup, "")
        if not backend_python(context):
            _text(layout, context, f"Set Up Backend installs {torch_build(context).describe()}")
            layout.operator("nerf.setup_backend", icon="CONSOLE")


class NERF_PT_training_preview(_NerfPanel, bpy.types.Panel):
    """The latest validation render, updated while training runs."""

    bl_label = "Live Preview"
    bl_parent_id = "NERF_PT_training"

    def draw(self, context):
        layout = self.layout
        preview = bpy.data.images.get(PREVIEW_IMAGE)
        if preview is None:
            layout.label(text="Shown once training validates", icon="INFO")
            return
        layout.template_icon(icon_value=preview.preview_ensure().icon_id, scale=8.0)
        _text(layout, context, f"Latest validation view (image '{PREVIEW_IMAGE}')")


class NERF_PT_results(_NerfPanel, bpy.types.Panel):
    bl_label = "Results"

    def draw(self, context):
        layout = self.layout
        col = layout.column(align=True)
        col.operator("nerf.render_test_views", icon="IMAGE_DATA")
        col.operator("nerf.render_active_camera", icon="CAMERA_DATA")
        layout.operator("nerf.compare", icon="ARROW_LEFTRIGHT")
        layout.operator("nerf.open_report", icon="URL")


class NERF_PT_results_animation(_NerfPanel, bpy.types.Panel):
    """The NeRF along the scene camera's animation, and its surface as a mesh or a baked asset."""

    bl_label = "Animation, Mesh and Asset"
    bl_parent_id = "NERF_PT_results"

    def draw(self, context):
        s, layout = context.scene.nerf, _split(self.layout)
        layout.prop(s, "animation_step")
        layout.prop(s, "animation_cycles")
        layout.prop(s, "animation_sequencer")
        _draw_job(layout, context, animation_dir(context), ("nerf.render_animation", "RENDER_ANIMATION"),
                  "nerf.cancel_animation", "No animation rendered")
        layout.separator()
        layout.prop(s, "mesh_resolution")
        layout.operator("nerf.import_mesh", icon="MESH_DATA")
        layout.separator()
        layout.prop(s, "asset_triangles")
        layout.prop(s, "asset_texture_size")
        _draw_job(layout, context, asset_dir(context), ("nerf.import_asset", "IMPORT"), "nerf.cancel_asset",
                  "No asset baked")


class NERF_PT_results_comparison(_NerfPanel, bpy.types.Panel):
    """The last Compare with Cycles: its numbers, and its image in the Image Editor."""

    bl_label = "Comparison"
    bl_parent_id = "NERF_PT_results"

    def draw(self, context):
        s, layout = context.scene.nerf, self.layout
        if not s.compare_metrics:
            layout.label(text="Compare with Cycles to see numbers", icon="INFO")
            return
        col = layout.column(align=True)
        for row in json.loads(s.compare_metrics):
            _value_row(col, row["label"], row["text"])
        if COMPARISON_IMAGE in bpy.data.images:
            _text(layout, context, f"Side by side: image '{COMPARISON_IMAGE}'", icon="IMAGE_DATA")


class NERF_PT_results_live_view(_NerfPanel, bpy.types.Panel):
    """The NeRF drawn in the 3D Views beside the scene, from any view (a render server)."""

    bl_label = "Live View"
    bl_parent_id = "NERF_PT_results"

    def draw(self, context):
        s, layout = context.scene.nerf, _split(self.layout)
        state = viewport_overlay.state()
        on = state in ("starting", "ready")
        text = "Stop Live View" if on else "Restart Live View" if state.startswith("stopped") else "Live View"
        layout.operator("nerf.live_view", text=text, icon="HIDE_OFF" if on else "HIDE_ON", depress=on)
        layout.prop(s, "live_view_anchor")
        if state == "starting":
            _text(layout, context, "Loading the model in the render server", icon="TIME")
        elif state == "ready":
            stats = viewport_overlay.stats
            rate = live_view_rate(stats.delivered_at, stats.render_seconds, stats.iteration, time.monotonic())
            _text(layout, context, rate, icon="CHECKMARK")
        elif state.startswith("stopped"):
            box = layout.box()
            box.alert = True
            _text(box, context, f"Live view {state}", icon="ERROR")


class NERF_PT_results_render(_NerfPanel, bpy.types.Panel):
    """The NeRF composited into F12 renders and animations by depth."""

    bl_label = "NeRF in Renders"
    bl_parent_id = "NERF_PT_results"

    def draw(self, context):
        s, layout = context.scene.nerf, _split(self.layout)
        on = s.render_composite
        layout.operator("nerf.render_composite", text="NeRF in Renders", icon="RENDER_STILL", depress=on)
        message = render_composite.last_message
        if message:
            box = layout.box()
            box.alert = message.startswith("no NeRF")
            _text(box, context, message, icon="ERROR" if box.alert else "CHECKMARK")
        elif on:
            _text(layout, context, "F12 renders the NeRF from the scene's camera, by depth with the scene",
                  icon="INFO")


CLASSES = (NERF_PT_dataset, NERF_PT_dataset_rendering, NERF_PT_training, NERF_PT_training_preview,
           NERF_PT_results, NERF_PT_results_comparison, NERF_PT_results_animation, NERF_PT_results_live_view,
           NERF_PT_results_render)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
