"""Live View: the run's NeRF drawn in every 3D View beside the scene (``viewport_overlay``),
rendered by the backend's ``serve`` in a process of its own, on a finished run or on one still
training (the server loads each new checkpoint). NeRF in Renders: the same server's frames
composited into F12 renders by depth (``render_composite``)."""

from __future__ import annotations

import bpy

from ..core.live_view import cannot_serve
from . import render_composite, viewport_overlay
from .paths import backend_python, run_dir, settings


def _cannot_serve(context) -> str:
    """Why the run cannot be served yet ("" where it can)."""
    return cannot_serve(backend_python(context), run_dir(context))


class NERF_OT_live_view(bpy.types.Operator):
    """Draw the run's NeRF in every 3D View, depth-tested against the scene (press again to
    stop; after the server stopped, press to start it again)"""

    bl_idname = "nerf.live_view"
    bl_label = "Live View"

    def execute(self, context):
        if viewport_overlay.state() in ("starting", "ready"):
            viewport_overlay.stop()
            return {"FINISHED"}
        reason = _cannot_serve(context)
        if reason:
            self.report({"ERROR"}, reason)
            return {"CANCELLED"}
        viewport_overlay.start(backend_python(context), run_dir(context), device=settings(context).train_device)
        return {"FINISHED"}


class NERF_OT_render_composite(bpy.types.Operator):
    """Composite the run's NeRF into F12 renders and animations by depth, over Cycles' or EEVEE's
    render of the scene from the same camera (adds its nodes to the scene's compositor; press
    again to remove them)"""

    bl_idname = "nerf.render_composite"
    bl_label = "NeRF in Renders"

    def execute(self, context):
        s = settings(context)
        if s.render_composite:
            render_composite.tear_down(context.scene)
            s.render_composite = False
            return {"FINISHED"}
        reason = _cannot_serve(context)
        if reason:
            self.report({"ERROR"}, reason)
            return {"CANCELLED"}
        try:
            render_composite.set_up(context.scene)
        except RuntimeError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        s.render_composite = True
        return {"FINISHED"}


CLASSES = (NERF_OT_live_view, NERF_OT_render_composite)
