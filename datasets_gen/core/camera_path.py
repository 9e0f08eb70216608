"""A Blender camera's animation as a NeRF camera path: per frame, the camera-to-world matrix in
a dataset's NeRF frame and the exact pixel intrinsics of that frame (lens, sensor and shift
may be animated). Pure maths and JSON, no bpy: the add-on and `datasets_gen --camera-path`
read the frames from Blender (blender/camera_animation.py) and write this document;
`python -m nerf_backend render RUN --camera-path FILE` renders it.

Example:
    >>> frames = parse_frames("1:5:2")
    >>> list(frames)
    [1, 3, 5]
    >>> pose = [[1, 0, 0, 2.0], [0, 1, 0, 0.0], [0, 0, 1, 1.0], [0, 0, 0, 1]]
    >>> frame = FrameCamera(1, pose, CameraSettings(resolution_x=80, resolution_y=60))
    >>> doc = camera_path_document("Camera", [frame], {"scale": 0.5, "translation": [0, 0, 0]}, fps=24.0)
    >>> doc["frames"][0]["transform_matrix"][0][3], doc["frames"][0]["w"], doc["frames"][0]["fl_x"]
    (1.0, 80, 111.11111111111111)
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

from nerf_contract.dataset_layout import CYCLES_FRAMES_DIR

from .intrinsics import CameraSettings
from .options import DatasetGenError

#: The document's name inside its folder, and the Cycles frames' folder beside it.
FORMAT = "nerf-from-blender camera path 1"


@dataclass(frozen=True)
class FrameCamera:
    """What Blender says of the camera at one frame: its world matrix and lens/render settings."""

    frame: int
    matrix_world: Sequence[Sequence[float]]
    camera: CameraSettings


def parse_frames(text: str) -> range:
    """``START:END[:STEP]``, both ends included as in Blender's frame range.

    Example:
        >>> parse_frames("10:12")
        range(10, 13)
    """
    match = re.fullmatch(r"\s*(-?\d+)\s*:\s*(-?\d+)\s*(?::\s*(\d+)\s*)?", text)
    if not match:
        raise DatasetGenError(f"--frames must look like START:END or START:END:STEP (e.g. 1:48:2), got {text!r}")
    start, end, step = int(match.group(1)), int(match.group(2)), int(match.group(3) or 1)
    if step < 1:
        raise DatasetGenError(f"--frames {text}: STEP must be at least 1")
    if end < start:
        raise DatasetGenError(f"--frames {text}: END comes before START")
    return range(start, end + 1, step)


def frame_stem(frame: int) -> str:
    """The file stem of a frame's images (``0007``; negative frames ``-007``), sorted in frame order."""
    return f"{frame:04d}"


def camera_to_nerf(matrix_world: Sequence[Sequence[float]], world_to_nerf: Mapping[str, Any]) -> list[list[float]]:
    """4×4 camera-to-world in the NeRF frame from Blender's ``matrix_world``.

    ``world_to_nerf`` is a dataset's record: ``p_nerf = scale · p_blender + translation``,
    rotations unchanged. The object's scale is removed (only rotation and position describe a
    camera); Blender and NeRF cameras share their convention (look down -Z, +Y up)."""
    scale = float(world_to_nerf.get("scale", 1.0))
    translation = [float(v) for v in world_to_nerf.get("translation", (0.0, 0.0, 0.0))]
    columns = []
    for axis in range(3):
        column = [float(matrix_world[row][axis]) for row in range(3)]
        length = math.sqrt(sum(c * c for c in column))
        if length <= 0 or not math.isfinite(length):
            raise DatasetGenError(f"camera matrix axis {axis} has length {length}: not a camera pose")
        columns.append([c / length for c in column])
    position = [scale * float(matrix_world[row][3]) + translation[row] for row in range(3)]
    return [[columns[0][row], columns[1][row], columns[2][row], position[row]] for row in range(3)] + \
        [[0.0, 0.0, 0.0, 1.0]]


def frame_entry(frame: FrameCamera, world_to_nerf: Mapping[str, Any], cycles: bool) -> dict[str, Any]:
    """One frame of the document: pose, intrinsics (as transforms.json names them) and lens."""
    intrinsics = frame.camera.intrinsics().as_dict()
    entry: dict[str, Any] = {"frame": frame.frame, **intrinsics,
                             "lens_mm": frame.camera.lens_mm,
                             "transform_matrix": camera_to_nerf(frame.matrix_world, world_to_nerf)}
    if cycles:
        entry["cycles_file_path"] = f"{CYCLES_FRAMES_DIR}/{frame_stem(frame.frame)}.png"
    return entry


def camera_path_document(
    camera_name: str, frames: Sequence[FrameCamera], world_to_nerf: Mapping[str, Any], fps: float,
    cycles: bool = False, dataset: Optional[str] = None,
) -> dict[str, Any]:
    """The camera-path JSON: one entry per frame, in the dataset's NeRF frame."""
    if not frames:
        raise DatasetGenError(f"camera path of {camera_name!r}: no frames")
    if not (fps > 0 and math.isfinite(fps)):
        raise DatasetGenError(f"camera path of {camera_name!r}: frame rate {fps} is not positive")
    sizes = {(frame.camera.intrinsics().w, frame.camera.intrinsics().h) for frame in frames}
    if len(sizes) > 1:
        raise DatasetGenError(f"camera path of {camera_name!r}: the image size changes between frames "
                              f"({', '.join(f'{w}×{h}' for w, h in sorted(sizes))}); a video keeps one size")
    return {
        "format": FORMAT,
        "camera": camera_name,
        "fps": fps,
        "dataset": dataset,
        "world_to_nerf": dict(world_to_nerf),
        "convention": "transform_matrix: camera-to-world in the NeRF frame (camera looks down -Z, +Y up); "
                      "w, h, fl_x, fl_y, cx, cy in pixels (origin top-left, y down) of that frame",
        "cycles": "cycles_file_path: Cycles' render of the frame with the dataset's settings" if cycles else None,
        "frames": [frame_entry(frame, world_to_nerf, cycles) for frame in frames],
    }
