"""Loading datasets in the nerf_synthetic layout, from this project or any other tool.

A dataset folder holds ``transforms_{split}.json`` (``camera_angle_x`` and ``frames`` with
``file_path`` and a camera-to-world ``transform_matrix``; optionally exact intrinsics
``fl_x, fl_y, cx, cy, w, h``), the RGBA PNGs those frames name (``file_path`` + ".png"),
and optionally ``scene_profile.json`` with the scene's bounds. Every problem raises
``DatasetError`` naming the file and what is wrong.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from .cameras import Intrinsics
from .errors import DatasetError


@dataclass
class DatasetSplit:
    """One split's cameras and images."""

    name: str
    intrinsics: Intrinsics
    poses: Tensor  # [N, 4, 4] float32 camera-to-world
    rgba: Tensor  # [N, H, W, 4] uint8, as on disk
    image_paths: list[Path]
    # Ground-truth depth EXR of each view (datasets_gen's ``depth_file_path``), None where absent.
    depth_paths: list[Path | None] = dataclasses.field(default_factory=list)

    def __len__(self) -> int:
        return self.poses.shape[0]

    def subset(self, count: int) -> "DatasetSplit":
        """The first ``count`` views."""
        return DatasetSplit(self.name, self.intrinsics, self.poses[:count], self.rgba[:count], self.image_paths[:count],
                            self.depth_paths[:count])

    def depth_path(self, index: int) -> Path | None:
        return self.depth_paths[index] if index < len(self.depth_paths) else None

    def rgb_on_white(self, index: int | slice | Tensor = slice(None)) -> Tensor:
        """Float RGB in [0, 1] composited over white, as the reference loaders do."""
        return composite(self.rgba[index])


@dataclass(frozen=True)
class SceneBounds:
    """Axis-aligned box holding the scene's renderable geometry, in the dataset's frame."""

    box_min: tuple[float, float, float]
    box_max: tuple[float, float, float]

    def padded(self, fraction: float) -> "SceneBounds":
        """The box grown on every side by ``fraction`` of its largest extent (geometry
        touches the bounds; a field needs a little room around it)."""
        size = max(hi - lo for lo, hi in zip(self.box_min, self.box_max))
        pad = fraction * size
        return SceneBounds(
            tuple(v - pad for v in self.box_min), tuple(v + pad for v in self.box_max)  # type: ignore[arg-type]
        )


def composite(rgba: Tensor, background: Tensor | float = 1.0) -> Tensor:
    """``uint8 [..., 4]`` → float RGB ``rgb·α + background·(1 − α)`` in [0, 1]
    (white by default, as the reference loaders)."""
    values = rgba.float() / 255.0
    alpha = values[..., 3:4]
    return values[..., :3] * alpha + background * (1.0 - alpha)


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return data


def _finite_number(data: dict, key: str, path: Path, positive: bool = True) -> float:
    value = data.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(f"{path}: '{key}' is missing or not a number")
    if not math.isfinite(value) or (positive and value <= 0):
        raise DatasetError(f"{path}: '{key}' must be a finite{' positive' if positive else ''} number, got {value}")
    return float(value)


def _pose(frame: dict, index: int, path: Path) -> np.ndarray:
    try:
        matrix = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{path}: frame {index} has no 4×4 numeric 'transform_matrix'") from None
    if matrix.shape != (4, 4):
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' is {matrix.shape}, expected 4×4")
    if not np.isfinite(matrix).all():
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' has NaN or infinite values")
    if abs(np.linalg.det(matrix[:3, :3])) < 1e-8:
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' is not invertible")
    return matrix


def _inside(dataset_dir: Path, relative: str, key: str, index: int, path: Path) -> Path:
    resolved = (dataset_dir / relative).resolve()
    if not resolved.is_relative_to(dataset_dir.resolve()):
        raise DatasetError(f"{path}: frame {index} '{key}' {relative!r} points outside the dataset folder")
    return resolved


def _image_path(dataset_dir: Path, frame: dict, index: int, path: Path) -> Path:
    file_path = frame.get("file_path")
    if not isinstance(file_path, str) or not file_path:
        raise DatasetError(f"{path}: frame {index} has no 'file_path'")
    relative = file_path if file_path.lower().endswith(".png") else file_path + ".png"
    return _inside(dataset_dir, relative, "file_path", index, path)


def _depth_path(dataset_dir: Path, frame: dict, index: int, path: Path) -> Path | None:
    depth_path = frame.get("depth_file_path")
    if depth_path is None:
        return None
    if not isinstance(depth_path, str) or not depth_path:
        raise DatasetError(f"{path}: frame {index} 'depth_file_path' must be a relative path")
    return _inside(dataset_dir, depth_path, "depth_file_path", index, path)


def _read_rgba(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: image not found")
    try:
        with Image.open(path) as image:
            mode = image.mode
            if mode not in ("RGBA", "LA", "RGB", "L", "P", "I;16", "I"):
                raise DatasetError(f"{path}: unsupported image mode {mode}")
            if mode in ("I;16", "I"):
                raise DatasetError(f"{path}: 16-bit images are not supported; write 8-bit RGBA PNG")
            if mode not in ("RGBA", "LA") and not (mode == "P" and "transparency" in image.info):
                raise DatasetError(f"{path}: image has no alpha channel ({mode}); expected RGBA as in nerf_synthetic")
            pixels = np.asarray(image.convert("RGBA"))
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise DatasetError(f"{path}: cannot read image ({exc})") from None
    return pixels


def read_intrinsics(data: dict, path: Path, width: int, height: int) -> Intrinsics:
    """Exact intrinsics if the JSON has them, else the reference loaders' from
    ``camera_angle_x``; checked against the images' size."""
    if all(key in data for key in ("fl_x", "fl_y", "cx", "cy")):
        intrinsics = Intrinsics(
            width, height,
            _finite_number(data, "fl_x", path), _finite_number(data, "fl_y", path),
            _finite_number(data, "cx", path, positive=False), _finite_number(data, "cy", path, positive=False),
        )
        for key, actual in (("w", width), ("h", height)):
            if key in data and int(data[key]) != actual:
                raise DatasetError(f"{path}: '{key}' is {data[key]} but the images are {width}×{height}")
        return intrinsics
    angle = _finite_number(data, "camera_angle_x", path)
    if angle >= math.pi:
        raise DatasetError(f"{path}: 'camera_angle_x' = {angle} is not a field of view below π")
    return Intrinsics.from_camera_angle_x(width, height, angle)


def load_split(dataset_dir: Path | str, split: str) -> DatasetSplit:
    """Read ``transforms_{split}.json`` and its images."""
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise DatasetError(f"{dataset_dir}: dataset folder not found")
    json_path = dataset_dir / f"transforms_{split}.json"
    data = _read_json(json_path)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{json_path}: 'frames' is missing or empty")
    if "camera_angle_x" not in data and "fl_x" not in data:
        raise DatasetError(f"{json_path}: 'camera_angle_x' is missing")
    poses, images, paths, depth_paths = [], [], [], []
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DatasetError(f"{json_path}: frame {index} is not an object")
        poses.append(_pose(frame, index, json_path))
        image_path = _image_path(dataset_dir, frame, index, json_path)
        pixels = _read_rgba(image_path)
        if images and pixels.shape != images[0].shape:
            raise DatasetError(
                f"{image_path}: size {pixels.shape[1]}×{pixels.shape[0]} differs from "
                f"{paths[0].name}'s {images[0].shape[1]}×{images[0].shape[0]}"
            )
        images.append(pixels)
        paths.append(image_path)
        depth_paths.append(_depth_path(dataset_dir, frame, index, json_path))
    height, width = images[0].shape[:2]
    return DatasetSplit(
        name=split,
        intrinsics=read_intrinsics(data, json_path, width, height),
        poses=torch.from_numpy(np.stack(poses)).float(),
        rgba=torch.from_numpy(np.stack(images)),
        image_paths=paths,
        depth_paths=depth_paths,
    )


@dataclass
class CameraPath:
    """Cameras without images: what to render (e.g. the Blender add-on's active camera)."""

    intrinsics: Intrinsics
    poses: Tensor  # [N, 4, 4] camera-to-world
    stems: list[str]


def load_cameras(json_path: Path | str) -> CameraPath:
    """Cameras from a transforms JSON that needs no images: it must give the image size
    (``w``, ``h``) and the intrinsics; frames may name their output (``file_path``)."""
    json_path = Path(json_path)
    data = _read_json(json_path)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{json_path}: 'frames' is missing or empty")
    try:
        width, height = int(data["w"]), int(data["h"])
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{json_path}: a camera file needs the image size as integers 'w' and 'h'") from None
    if width < 1 or height < 1:
        raise DatasetError(f"{json_path}: image size {width}×{height} is empty")
    poses, stems = [], []
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DatasetError(f"{json_path}: frame {index} is not an object")
        poses.append(_pose(frame, index, json_path))
        name = frame.get("file_path")
        stems.append(Path(name).stem if isinstance(name, str) and name else f"view_{index:03d}")
    return CameraPath(read_intrinsics(data, json_path, width, height), torch.from_numpy(np.stack(poses)).float(), stems)


def load_scene_profile(dataset_dir: Path | str) -> dict | None:
    """``scene_profile.json`` as written by datasets_gen, or None for other tools' datasets."""
    path = Path(dataset_dir) / "scene_profile.json"
    return _read_json(path) if path.exists() else None


def load_scene_bounds(dataset_dir: Path | str) -> SceneBounds | None:
    """The bounds from ``scene_profile.json``, or None when the dataset has none (datasets
    from other tools)."""
    path = Path(dataset_dir) / "scene_profile.json"
    if not path.exists():
        return None
    bounds = _read_json(path).get("bounds")
    try:
        box_min = tuple(float(v) for v in bounds["min"])
        box_max = tuple(float(v) for v in bounds["max"])
    except (TypeError, KeyError, ValueError):
        raise DatasetError(f"{path}: 'bounds' must hold 'min' and 'max' as three numbers each") from None
    if len(box_min) != 3 or len(box_max) != 3 or not all(map(math.isfinite, box_min + box_max)):
        raise DatasetError(f"{path}: 'bounds' must hold 'min' and 'max' as three finite numbers each")
    if any(lo >= hi for lo, hi in zip(box_min, box_max)):
        raise DatasetError(f"{path}: 'bounds' min {box_min} is not below max {box_max}")
    return SceneBounds(box_min, box_max)  # type: ignore[arg-type]
