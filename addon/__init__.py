"""The Blender add-on (View3D › Sidebar › NeRF): generate a dataset, train, watch it learn,
compare with Cycles.

Its code is of two kinds, each in a package of its own:

- ``core/``: plain Python, never ``bpy``, ``mathutils`` or ``gpu``, tested without Blender: the
  background jobs (``jobs``), Set Up Backend and its PyTorch build (``backend_setup``,
  ``torch_builds``), the live view's client and scheduler (``live_view``), the frames' pixels
  for the compositor (``composite_pixels``), where the backends are (``sources``) and the
  panel's wording (``panel_text``).
- ``blender/``: what runs only inside Blender, which draws and calls ``core``: the settings
  (``properties``), the buttons (``operators``, by concern in the ``*_ops`` modules), the panel
  (``panel``, ``ui_text``), the timer that polls the jobs (``job_timer``), the live view's
  drawing (``viewport_overlay``), the NeRF in F12 renders (``render_composite``), and what they
  share (``paths``, ``images``, ``scene_import``).

``tests/test_import_graph.py`` keeps ``core`` from importing Blender's modules or ``blender``.
The add-on reaches the backends only through static imports of ``nerf_contract`` (file names,
events, command lines) and ``datasets_gen`` (its options, camera maths, and in Blender its
scene checks and renders). It never imports torch: training runs in the backend's own Python
as a separate process.
"""

def register() -> None:
    # Here, not at the top: importing ``addon.core`` (the tests, without Blender) runs this file.
    from .blender import operators, panel, properties

    for module in (properties, operators, panel):
        module.register()


def unregister() -> None:
    from .blender import operators, panel, properties

    for module in (panel, operators, properties):
        module.unregister()
