"""The add-on's Blender-facing side: registration, properties, operators, the panel's drawing,
timers and draw handlers. Runs only inside Blender; what it decides or computes without Blender
is in ``addon.core``."""
