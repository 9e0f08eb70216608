"""The Blender add-on (View3D › Sidebar › NeRF): generate a dataset, train, watch it learn,
compare with Cycles.

Blender-facing code (``properties``, ``operators`` with the buttons in ``dataset_ops``,
``training_ops``, ``results_ops``, ``animation_ops`` and ``live_view_ops``, ``job_timer``,
``paths``, ``images``, ``panel``, ``viewport_overlay``, the live view's drawing, and
``render_composite``, the NeRF in F12 renders) only draws and calls; the job handling
(``jobs``, ``backend_setup``), the live view's client and scheduler (``live_view``) and the
frames' conversion for the compositor (``composite_pixels``) are plain Python that tests drive
without Blender. The add-on reaches the backends only through static imports of
``nerf_contract`` (file names, events, command lines) and ``datasets_gen`` (its options, camera
maths, and in Blender its scene checks and renders). It never imports torch: training runs in
the backend's own Python as a separate process.
"""

def register() -> None:
    # Here, not at the top: the plain modules (jobs, backend_setup...) are imported without bpy.
    from . import operators, panel, properties

    for module in (properties, operators, panel):
        module.register()


def unregister() -> None:
    from . import operators, panel, properties

    for module in (panel, operators, properties):
        module.unregister()
