"""View3D › Sidebar › NeRF: dataset, training, results. Drawing only; the buttons are in
``operators`` and the job state comes from its last poll."""

from __future__ import annotations

import textwrap

import bpy

from . import operators


def _draw_status(layout, state, idle_text: str) -> None:
    if state is None or state.state == "idle":
        layout.label(text=idle_text)
        return
    if state.state == "running":
        left = f", {state.seconds_left:.0f} s left" if state.seconds_left is not None else ""
        layout.progress(factor=state.fraction, type="BAR", text=f"{state.detail}{left}")
    elif state.state == "failed":
        box = layout.box()
        box.label(text="Failed:", icon="ERROR")
        lines = [wrapped for line in state.error.splitlines() for wrapped in textwrap.wrap(line, 60) or [""]]
        for line in lines[-8:]:
            box.label(text=line)
    else:
        layout.label(text=f"{state.state.capitalize()}: {state.detail}", icon="CHECKMARK" if state.state == "done" else "PAUSE")
    if state.warning and state.state != "failed":
        box = layout.box()
        for number, line in enumerate(textwrap.wrap(state.warning, 60)[:6]):
            box.label(text=line, icon="ERROR" if number == 0 else "NONE")


class _NerfPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeRF"


class NERF_PT_dataset(_NerfPanel, bpy.types.Panel):
    bl_label = "Dataset"

    def draw(self, context):
        s, layout = context.scene.nerf, self.layout
        layout.prop(s, "dataset_dir")
        row = layout.row(align=True)
        for name in ("train_views", "val_views", "test_views"):
            row.prop(s, name)
        layout.prop(s, "resolution")
        row = layout.row(align=True)
        row.prop(s, "samples")
        row.prop(s, "render_device", text="")
        layout.prop(s, "sphere")
        layout.prop(s, "depth_normals")
        layout.prop(s, "seed")
        folder = str(operators.dataset_dir(context))
        running = operators.status.get(folder)
        layout.operator("nerf.generate_dataset", icon="RENDER_STILL")
        _draw_status(layout, running, "No dataset rendering")


class NERF_PT_training(_NerfPanel, bpy.types.Panel):
    bl_label = "Training"

    def draw(self, context):
        s, layout = context.scene.nerf, self.layout
        layout.prop(s, "run_dir")
        layout.prop(s, "preset")
        row = layout.row(align=True)
        row.prop(s, "budget_kind", expand=True)
        layout.prop(s, "budget_seconds" if s.budget_kind == "TIME" else "budget_iterations")
        layout.prop(s, "train_device")
        state = operators.status.get(str(operators.run_dir(context)))
        row = layout.row(align=True)
        if state is not None and state.state == "running":
            row.operator("nerf.cancel_training", icon="CANCEL")
        else:
            row.operator("nerf.train", icon="PLAY").resume = False
            row.operator("nerf.train", text="Resume", icon="FILE_REFRESH").resume = True
        _draw_status(layout, state, "Not training")
        preview = bpy.data.images.get(operators.PREVIEW_IMAGE)
        if preview is not None:
            layout.template_icon(icon_value=preview.preview_ensure().icon_id, scale=6.0)
            layout.label(text=f"Latest validation render (image '{operators.PREVIEW_IMAGE}')")
        setup = operators.status.get("backend-setup")
        if setup is not None:
            _draw_status(layout, setup, "")
        if not operators.backend_python(context):
            layout.operator("nerf.setup_backend", icon="CONSOLE")


class NERF_PT_results(_NerfPanel, bpy.types.Panel):
    bl_label = "Results"

    def draw(self, context):
        s, layout = context.scene.nerf, self.layout
        layout.operator("nerf.render_test_views", icon="IMAGE_DATA")
        layout.operator("nerf.render_active_camera", icon="CAMERA_DATA")
        layout.operator("nerf.compare", icon="ARROW_LEFTRIGHT")
        if s.compare_lpips:
            col = layout.column(align=True)
            col.label(text=f"PSNR {s.compare_psnr:.2f} dB   SSIM {s.compare_ssim:.4f}")
            col.label(text=f"LPIPS {s.compare_lpips}")
        layout.operator("nerf.open_report", icon="URL")


CLASSES = (NERF_PT_dataset, NERF_PT_training, NERF_PT_results)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
