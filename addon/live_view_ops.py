"""Live View: the run's NeRF drawn in every 3D View beside the scene (``viewport_overlay``),
rendered by the backend's ``serve`` in a process of its own, on a finished run or on one still
training (the server loads each new checkpoint)."""

from __future__ import annotations

import bpy

from nerf_contract.run_layout import CHECKPOINT_NAME

from . import viewport_overlay
from .paths import backend_python, run_dir, settings


class NERF_OT_live_view(bpy.types.Operator):
    """Draw the run's NeRF in every 3D View, depth-tested against the scene (press again to
    stop; after the server stopped, press to start it again)"""

    bl_idname = "nerf.live_view"
    bl_label = "Live View"

    def execute(self, context):
        if viewport_overlay.state() in ("starting", "ready"):
            viewport_overlay.stop()
            return {"FINISHED"}
        python, run = backend_python(context), run_dir(context)
        if not python:
            self.report({"ERROR"}, "no backend Python: press Set Up Backend, or choose one in the preferences")
            return {"CANCELLED"}
        if not (run / CHECKPOINT_NAME).is_file():
            self.report({"ERROR"}, f"{run}: no checkpoint yet: train first (the live view also follows a run "
                                   "while it trains, from its first checkpoint)")
            return {"CANCELLED"}
        viewport_overlay.start(python, run, device=settings(context).train_device)
        return {"FINISHED"}


CLASSES = (NERF_OT_live_view,)
