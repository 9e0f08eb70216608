"""The Blender add-on (View3D › Sidebar › NeRF).

Blender-facing code only: it never imports torch. It renders datasets with ``datasets_gen``
and drives the training backend (``nerf_backend``) as a separate process.

This is the package's skeleton: it registers nothing yet. The sidebar panel (generate,
train with live progress and cancel, load renders, compare with Cycles) is issue #6; until
then the command lines in the README do each step.
"""

_CLASSES: tuple = ()


def register() -> None:
    import bpy

    for cls in _CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    import bpy

    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
