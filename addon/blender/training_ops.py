"""Train, Resume and Cancel (training runs in the backend's Python, a separate process), and
Set Up Backend (the Python environment that trains)."""

from __future__ import annotations

import bpy

from ..core import sources
from ..core.backend_setup import BackendSetup, check_backend
from ..core.jobs import default_base_python, training_cpu_threads
from .job_timer import backend_setup, ensure_timer, training_job, watch_backend_setup
from .paths import backend_python, dataset_dir, managed_venv, settings, torch_build


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
        job.start(python, sources.backend_root(), dataset_dir(context), s.preset,
                  iterations=None if by_time else s.budget_iterations,
                  max_seconds=s.budget_seconds if by_time else None,
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


class NERF_OT_setup_backend(bpy.types.Operator):
    """Create a Python environment with the backend's packages for training, with the PyTorch
    build for this machine's GPU (the preferences can force another)"""

    bl_idname = "nerf.setup_backend"
    bl_label = "Set Up Backend"

    def execute(self, context):
        previous = backend_setup()
        if previous is not None and previous.poll().state == "running":
            self.report({"ERROR"}, "the backend is already being set up")
            return {"CANCELLED"}
        setup = BackendSetup(managed_venv(), default_base_python(), sources.backend_requirements(),
                             torch_build(context), sources.backend_root())
        watch_backend_setup(setup)
        try:
            setup.start()
        except (OSError, RuntimeError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        ensure_timer()
        return {"FINISHED"}


CLASSES = (NERF_OT_train, NERF_OT_cancel_training, NERF_OT_setup_backend)
