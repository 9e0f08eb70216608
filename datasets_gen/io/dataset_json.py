"""The JSON documents of a dataset, built as plain dicts (no bpy, no I/O).

transforms_{split}.json follows the nerf_synthetic layout that every common loader reads
(`camera_angle_x` + `frames` with `file_path` without extension and a 4x4 camera-to-world
`transform_matrix`), extended with explicit pixel intrinsics (`fl_x`, `fl_y`, `cx`, `cy`,
`w`, `h`, as instant-ngp/nerfstudio name them) and a `generator` record of every setting.

Every document also carries `world_to_nerf`, the similarity that maps Blender's world into the
frame the poses are written in (see frame_fit), so Blender cameras can be mapped in and out.

scene_profile.json tells the backend what the scene needs: where the geometry is (bounds in the
NeRF frame), whether any material is view-dependent or transparent, lights, world, sizes.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence

from ..core.intrinsics import Intrinsics

SCENE_PROFILE_VERSION = 2


def frame_file_path(split: str, index: int) -> str:
    """The `file_path` of a frame: relative, "./" prefixed, no extension (loaders append ".png")."""
    return f"./{split}/r_{index}"


def depth_file_path(split: str, index: int) -> str:
    """Relative path of a view's depth EXR (with its extension: it is not a PNG)."""
    return f"./{split}/r_{index}_depth.exr"


def normal_file_path(split: str, index: int) -> str:
    """Relative path of a view's normal EXR."""
    return f"./{split}/r_{index}_normal.exr"


def frame_index(file_path: str) -> int:
    """The view index in a frame's `file_path` ("./train/r_12" -> 12)."""
    return int(file_path.rsplit("r_", 1)[1])


def frame_entry(
    split: str, index: int, rotation: float, matrix: Sequence[Sequence[float]], depth_normals: bool = False
) -> dict:
    """One element of `frames`; `depth_normals` adds the paths of its depth and normal EXRs."""
    entry = {
        "file_path": frame_file_path(split, index),
        "rotation": float(rotation),
        "transform_matrix": [[float(value) for value in row] for row in matrix],
    }
    if depth_normals:
        entry["depth_file_path"] = depth_file_path(split, index)
        entry["normal_file_path"] = normal_file_path(split, index)
    return entry


def transforms_document(
    intrinsics: Intrinsics,
    frames: Sequence[Mapping[str, Any]],
    generator: Mapping[str, Any],
    world_to_nerf: Mapping[str, Any],
    depth_normals_layout: Optional[Mapping[str, Any]] = None,
) -> dict:
    """A whole transforms_{split}.json document."""
    document: dict = {"camera_angle_x": intrinsics.camera_angle_x}
    document.update(intrinsics.as_dict())
    document["world_to_nerf"] = dict(world_to_nerf)
    if depth_normals_layout is not None:
        document["depth_normals"] = dict(depth_normals_layout)
    document["frames"] = [dict(frame) for frame in frames]
    document["generator"] = dict(generator)
    return document


def scene_profile(
    source: str, bounds_min: Sequence[float], bounds_max: Sequence[float], **details: Any
) -> dict:
    """scene_profile.json: bounds of the rendered geometry in the NeRF frame, then `details`."""
    profile = {
        "version": SCENE_PROFILE_VERSION,
        "source": source,
        "bounds": {
            "min": [float(value) for value in bounds_min],
            "max": [float(value) for value in bounds_max],
        },
    }
    profile.update(details)
    return profile
