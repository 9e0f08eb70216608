"""A Blender camera as a NeRF camera file: the pose mapped into the dataset's NeRF frame and
exact intrinsics at the dataset's resolution. Pure maths (lists of floats), no bpy.

The dataset records ``world_to_nerf``: ``p_nerf = scale · p_blender + translation`` with
rotations unchanged, so a camera-to-world matrix keeps its (unit-length) rotation columns
and maps its position. Blender cameras and NeRF cameras share the convention (look down -Z,
+Y up), so nothing else changes.
"""

from __future__ import annotations

import math
from typing import Sequence


def camera_to_nerf(matrix_world: Sequence[Sequence[float]], world_to_nerf: dict) -> list[list[float]]:
    """4×4 camera-to-world in the NeRF frame from Blender's ``matrix_world`` (object scale
    removed: only rotation and position describe a camera)."""
    scale = float(world_to_nerf.get("scale", 1.0))
    translation = [float(v) for v in world_to_nerf.get("translation", (0.0, 0.0, 0.0))]
    columns = []
    for axis in range(3):
        column = [float(matrix_world[row][axis]) for row in range(3)]
        length = math.sqrt(sum(c * c for c in column))
        if length <= 0 or not math.isfinite(length):
            raise ValueError(f"camera matrix axis {axis} has length {length}: not a camera pose")
        columns.append([c / length for c in column])
    position = [scale * float(matrix_world[row][3]) + translation[row] for row in range(3)]
    return [[columns[0][row], columns[1][row], columns[2][row], position[row]] for row in range(3)] + [[0.0, 0.0, 0.0, 1.0]]


def camera_file(matrix_world: Sequence[Sequence[float]], world_to_nerf: dict, intrinsics: dict, stem: str) -> dict:
    """The transforms-style JSON ``python -m nerf_backend render --cameras`` reads: one frame.

    ``intrinsics``: ``w, h, fl_x, fl_y, cx, cy`` (datasets_gen's ``Intrinsics.as_dict()``)."""
    keys = ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_angle_x")
    return {**{k: intrinsics[k] for k in keys if k in intrinsics},
            "frames": [{"file_path": f"./{stem}", "transform_matrix": camera_to_nerf(matrix_world, world_to_nerf)}]}
