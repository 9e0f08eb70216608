"""The Blender add-on (View3D › Sidebar › NeRF): generate a dataset, train, watch it learn,
compare with Cycles.

Blender-facing code (``properties``, ``operators`` with the buttons in ``dataset_ops``,
``training_ops`` and ``results_ops``, ``job_timer``, ``paths``, ``images``, ``panel``) only
draws and calls; the job handling (``jobs``, ``backend_setup``) is plain Python that tests
drive without Blender, and the camera maths is ``datasets_gen``'s (``camera_path``). The add-on never
imports torch: training runs in the backend's own Python as a separate process.
"""

_MODULES = ("properties", "operators", "panel")


def register() -> None:
    import importlib

    for name in _MODULES:
        importlib.import_module(f".{name}", __package__).register()


def unregister() -> None:
    import importlib

    for name in reversed(_MODULES):
        importlib.import_module(f".{name}", __package__).unregister()
