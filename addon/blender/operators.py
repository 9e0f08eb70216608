"""The panel's buttons, collected for registration. Long work runs in other processes (a
background Blender renders the dataset, the backend's Python trains); a timer polls them
through ``core.jobs`` and redraws (``job_timer``). Blender never waits on them, except where no
Blender binary exists to spawn (the ``bpy`` module), where the dataset is rendered in this
process.

By concern: ``dataset_ops`` (Generate Dataset), ``training_ops`` (Train, Resume, Cancel, Set
Up Backend), ``results_ops`` (Render Test Views, Render Active Camera, Compare with Cycles,
Open Report), ``animation_ops`` (Render Camera Animation, its Cancel, Import NeRF Mesh, Import
NeRF Asset and its Cancel), ``live_view_ops`` (Live View, drawn by ``viewport_overlay``);
``render_composite`` has no button (NeRF in Renders is a setting): its compositor nodes and
render handlers put the NeRF into F12. ``paths``, ``images`` and ``scene_import`` are what
they share."""

from __future__ import annotations

import bpy

from . import (animation_ops, dataset_ops, job_timer, live_view_ops, render_composite, results_ops, training_ops,
               viewport_overlay)

CLASSES = (*dataset_ops.CLASSES, *training_ops.CLASSES, *results_ops.CLASSES, *animation_ops.CLASSES,
           *live_view_ops.CLASSES)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    job_timer.register()
    viewport_overlay.register()
    render_composite.register()


def unregister() -> None:
    render_composite.unregister()
    viewport_overlay.unregister()
    job_timer.unregister()
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
