"""Render NeRF datasets from Blender, faithful to the Realistic Synthetic 360 (nerf_synthetic) protocol.

In layers, lowest first, as Blender's glTF add-on keeps ``io/`` apart from ``blender/``:

- ``core``: options, camera rig, intrinsics, frame fit, camera-path maths, scene checks,
  voxelising, z-buffer (plain Python, no files);
- ``io``: the dataset folder and every file written into it (plain Python);
- ``blender``: the scene's facts, bounds and occupancy, rendering, the scenes built in code (bpy);
- at the top, the pipelines and commands: ``generator`` (one dataset; ``generate_dataset`` is
  the in-process entry point, ``scene`` renders the open scene), ``suite`` (--suite),
  ``camera_path_export`` (--camera-path) and ``cli``.

Command lines: ``python -m datasets_gen`` and ``blender -b [SCENE.blend] --python
datasets_gen/generate.py -- ...``.

Importing the package, ``core`` or ``io`` does not import bpy (the pipelines import the
``blender`` layer only when they run), so the plain parts work in any Python.
"""

from .core.options import DatasetGenError
from .generator import generate_dataset

__all__ = ["DatasetGenError", "generate_dataset"]
