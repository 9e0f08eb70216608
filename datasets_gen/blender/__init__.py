"""The generator's Blender side (imports bpy): what the scene is (`scene_facts`, `scene_bounds`,
`scene_occupancy`), undoable changes to it (`scene_state`), rendering a view (`render`), an
animated camera (`camera_animation`), differences between Blender versions (`compat`), and the
scenes built in code (`demo_scene`, `trap_scenes`, `builtin_scenes`). Imports `core` and `io`;
imported only inside Blender (Blender's own Python or the bpy module)."""
