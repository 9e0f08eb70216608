"""Render NeRF datasets from Blender, faithful to the Realistic Synthetic 360 (nerf_synthetic) protocol.

Pure maths (no bpy): `trajectories` (camera rig and views), `intrinsics` (pixel intrinsics of a
Blender camera), `dataset_json` (the JSON documents), `options`.  Blender-facing: `demo_scene`,
`blender_render`, `scene_bounds`; `generator.generate_dataset` is the in-process entry point.
Command lines: `python -m datasets_gen` and `blender -b --python datasets_gen/generate.py -- ...`.

Importing the package does not import bpy (the generator imports it only when it runs), so the
pure parts work in any Python.
"""

from .generator import generate_dataset
from .options import DatasetGenError

__all__ = ["DatasetGenError", "generate_dataset"]
