"""The JSON documents of a dataset, built as plain dicts (no bpy, no I/O).

transforms_{split}.json follows the nerf_synthetic layout that every common loader reads
(`camera_angle_x` + `frames` with `file_path` without extension and a 4x4 camera-to-world
`transform_matrix`), extended with explicit pixel intrinsics (`fl_x`, `fl_y`, `cx`, `cy`,
`w`, `h`, as instant-ngp/nerfstudio name them) and a `generator` record of every setting.

scene_profile.json tells the backend where the geometry is; later issues add keys to the dict
returned by `scene_profile`, hence a builder rather than a fixed schema in the writer.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

from .intrinsics import Intrinsics

SCENE_PROFILE_VERSION = 1


def frame_file_path(split: str, index: int) -> str:
    """The `file_path` of a frame: relative, "./" prefixed, no extension (loaders append ".png")."""
    return f"./{split}/r_{index}"


def frame_entry(split: str, index: int, rotation: float, matrix: Sequence[Sequence[float]]) -> dict:
    """One element of `frames`."""
    return {
        "file_path": frame_file_path(split, index),
        "rotation": float(rotation),
        "transform_matrix": [[float(value) for value in row] for row in matrix],
    }


def transforms_document(
    intrinsics: Intrinsics, frames: Sequence[Mapping[str, Any]], generator: Mapping[str, Any]
) -> dict:
    """A whole transforms_{split}.json document."""
    document: dict = {"camera_angle_x": intrinsics.camera_angle_x}
    document.update(intrinsics.as_dict())
    document["frames"] = [dict(frame) for frame in frames]
    document["generator"] = dict(generator)
    return document


def scene_profile(
    source: str, bounds_min: Sequence[float], bounds_max: Sequence[float]
) -> dict:
    """scene_profile.json: where the rendered geometry is (world space, axis-aligned)."""
    return {
        "version": SCENE_PROFILE_VERSION,
        "source": source,
        "bounds": {
            "min": [float(value) for value in bounds_min],
            "max": [float(value) for value in bounds_max],
        },
    }
