"""The add-on's plain Python: decisions, computations, formats and processes that need no
Blender. Never imports ``bpy``, ``mathutils``, ``gpu`` or anything of ``addon.blender``
(tests/test_import_graph.py), so every module here is tested in any Python."""
