"""Render NeRF datasets from Blender, faithful to the Realistic Synthetic 360 (nerf_synthetic) protocol.

Pure (no bpy, standard library only): `trajectories` (camera rig and views), `intrinsics` (pixel
intrinsics of a Blender camera), `frame_fit` (the similarity into the protocol's frame),
`scene_checks` (what refuses a scene), `materials` (view dependence and transparency),
`depth_normals` and `exr` (the depth/normal files), `png_check`, `dataset_json` (the JSON
documents), `options` (GeneratorOptions, with each one's flag and keyword), `output_dir`
(folder, resume, progress file), `shards` (--merge), `builtin_scenes` (the registry of scenes
built in code).
Blender-facing: `scene_facts`, `scene_bounds`, `scene_state` (undoable changes), `blender_render`,
`demo_scene` and `trap_scenes` (the scenes built in code), `suite` (--suite);
`generator.generate_dataset` is the in-process entry point (options as keywords; `scene` renders
the open scene).
Command lines: `python -m datasets_gen` and `blender -b [SCENE.blend] --python
datasets_gen/generate.py -- ...`.

Importing the package does not import bpy (the generator imports it only when it runs), so the
pure parts work in any Python.
"""

from .generator import generate_dataset
from .options import DatasetGenError

__all__ = ["DatasetGenError", "generate_dataset"]
