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
import struct
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path, PurePath

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch import Tensor

from nerf_contract.dataset_layout import PROFILE_NAME, transforms_name

from ..core.cameras import Intrinsics
from ..core.errors import DatasetError
from ..core.scene_bounds import SceneBounds


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


def composite(rgba: Tensor, background: Tensor | float = 1.0) -> Tensor:
    """``uint8 [..., 4]`` → float RGB ``rgb·α + background·(1 − α)`` in [0, 1]
    (white by default, as the reference loaders)."""
    values = rgba.float() / 255.0
    alpha = values[..., 3:4]
    return values[..., :3] * alpha + background * (1.0 - alpha)


# Every tensor the backend builds from a dataset is float32: a number beyond its range
# would become infinite there, so it is refused here.
_FLOAT32_MAX = float(np.finfo(np.float32).max)
# Blender's largest render resolution; a camera file asking for more is a mistake.
MAX_IMAGE_SIDE = 65536
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _one_line(text: object) -> str:
    """Another library's error text on one line (the CLI prints every error as one line)."""
    return " ".join(str(text).split())


def _show(value: object) -> str:
    """A JSON value for a message: its repr (one line), its middle cut out when long."""
    text = repr(value)
    return text if len(text) <= 200 else f"{text[:80]}...{text[-80:]}"


def _as_float(value: object) -> float | None:
    """A JSON number as a float (an int too large for a float becomes ±inf); None for
    anything else, bools included (JSON ``true`` is not the number 1)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


def _in_range(number: float) -> bool:
    return math.isfinite(number) and abs(number) <= _FLOAT32_MAX


def _require_file(path: Path, what: str) -> None:
    try:
        if path.is_file():
            return
        is_dir = path.is_dir()
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or exc
        raise DatasetError(f"{path}: {what} cannot be opened ({_one_line(reason)})") from None
    raise DatasetError(f"{path}: expected a file, found a folder" if is_dir else f"{path}: {what} not found")


def _read_json(path: Path) -> dict:
    _require_file(path, "file")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read file ({_one_line(exc.strerror or exc)})") from None
    try:
        data = json.loads(raw)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, UnicodeDecodeError, too deep, too many digits
        raise DatasetError(f"{path}: not valid JSON ({_one_line(exc) or type(exc).__name__})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level, got {type(data).__name__}")
    return data


def _finite_number(data: dict, key: str, path: Path, positive: bool = True) -> float:
    if key not in data:
        raise DatasetError(f"{path}: '{key}' is missing")
    value = data[key]
    number = _as_float(value)
    if number is None:
        raise DatasetError(f"{path}: '{key}' must be a number, got {_show(value)}")
    if not math.isfinite(number) or (positive and number <= 0):
        kind = "finite positive" if positive else "finite"
        raise DatasetError(f"{path}: '{key}' must be a {kind} number, got {_show(value)}")
    if abs(number) > _FLOAT32_MAX:
        raise DatasetError(f"{path}: '{key}' = {_show(value)} is beyond float32's range")
    return number


def _image_side(data: dict, key: str, path: Path) -> int:
    """``w`` or ``h``: a whole number of pixels (``40`` or ``40.0``), at least 1."""
    value = data[key]
    number = _as_float(value)
    if number is None or not math.isfinite(number) or number != int(number) or number < 1:
        raise DatasetError(f"{path}: '{key}' must be a whole number of pixels, got {_show(value)}")
    if number > MAX_IMAGE_SIDE:
        raise DatasetError(f"{path}: '{key}' = {int(number)} pixels is above the largest image side, {MAX_IMAGE_SIDE}")
    return int(number)


def _frames(data: dict, path: Path) -> list:
    if "frames" not in data:
        raise DatasetError(f"{path}: 'frames' is missing")
    frames = data["frames"]
    if not isinstance(frames, list):
        raise DatasetError(f"{path}: 'frames' must be a list of frames, got {_show(frames)}")
    if not frames:
        raise DatasetError(f"{path}: 'frames' is empty")
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DatasetError(f"{path}: frame {index} is not an object")
    return frames


def _pose(frame: dict, index: int, path: Path) -> np.ndarray:
    rows = frame.get("transform_matrix")
    if rows is None:
        raise DatasetError(f"{path}: frame {index} has no 'transform_matrix'")
    if not (isinstance(rows, list) and len(rows) == 4 and all(isinstance(row, list) and len(row) == 4 for row in rows)):
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' is not a 4×4 list of lists")
    values = [_as_float(value) for row in rows for value in row]
    if any(value is None for value in values):
        bad = next(value for row in rows for value in row if _as_float(value) is None)
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' holds {_show(bad)}, not a number")
    matrix = np.array(values, dtype=np.float64).reshape(4, 4)
    if not np.isfinite(matrix).all():
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' has NaN or infinite values")
    if np.abs(matrix).max() > _FLOAT32_MAX:
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' has values beyond float32's range")
    matrix = matrix.astype(np.float32).astype(np.float64)  # what the backend will use
    determinant = np.linalg.det(matrix[:3, :3])
    if not (math.isfinite(determinant) and abs(determinant) >= 1e-8):
        raise DatasetError(f"{path}: frame {index} 'transform_matrix' is not invertible (its rotation part has "
                           f"determinant {determinant:.3g})")
    return matrix


def _inside(dataset_dir: Path, relative: str, key: str, index: int, path: Path) -> Path:
    if "\x00" in relative:
        raise DatasetError(f"{path}: frame {index} '{key}' {_show(relative)} contains a NUL character")
    try:
        resolved = (dataset_dir / relative).resolve()
    except (OSError, ValueError, RuntimeError) as exc:  # name too long, symlink loop
        reason = getattr(exc, "strerror", None) or exc
        raise DatasetError(f"{path}: frame {index} '{key}' {_show(relative)} is not a usable path "
                           f"({_one_line(reason)})") from None
    if not resolved.is_relative_to(dataset_dir.resolve()):
        raise DatasetError(f"{path}: frame {index} '{key}' {_show(relative)} points outside the dataset folder")
    return resolved


def _image_path(dataset_dir: Path, frame: dict, index: int, path: Path) -> Path:
    file_path = frame.get("file_path")
    if file_path is None:
        raise DatasetError(f"{path}: frame {index} has no 'file_path'")
    if not isinstance(file_path, str) or not file_path:
        raise DatasetError(f"{path}: frame {index} 'file_path' must be a relative path, got {_show(file_path)}")
    relative = file_path if file_path.lower().endswith(".png") else file_path + ".png"
    return _inside(dataset_dir, relative, "file_path", index, path)


def _depth_path(dataset_dir: Path, frame: dict, index: int, path: Path) -> Path | None:
    depth_path = frame.get("depth_file_path")
    if depth_path is None:
        return None
    if not isinstance(depth_path, str) or not depth_path:
        raise DatasetError(f"{path}: frame {index} 'depth_file_path' must be a relative path, got {_show(depth_path)}")
    return _inside(dataset_dir, depth_path, "depth_file_path", index, path)


def _read_rgba(path: Path) -> np.ndarray:
    _require_file(path, "image")
    try:
        with open(path, "rb") as handle:
            head = handle.read(26)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read image ({_one_line(exc.strerror or exc)})") from None
    if not head:
        raise DatasetError(f"{path}: image file is empty (0 bytes); expected an 8-bit RGBA PNG")
    if head.startswith(_PNG_SIGNATURE):
        # Pillow opens a 16-bit RGBA PNG as 8-bit "RGBA", silently: the bit depth is
        # IHDR's byte (8 signature + 4 length + 4 "IHDR" + 4 width + 4 height = byte 24).
        if len(head) < 25 or head[12:16] != b"IHDR":
            raise DatasetError(f"{path}: PNG is truncated or damaged (no IHDR header)")
        if head[24] == 16:
            raise DatasetError(f"{path}: 16-bit PNG is not supported; write 8-bit RGBA PNGs")
    try:
        with Image.open(path) as image:
            mode = image.mode
            if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
                raise DatasetError(f"{path}: 16-bit image ({mode}) is not supported; write 8-bit RGBA PNGs")
            if mode not in ("RGBA", "LA", "RGB", "L", "P"):
                raise DatasetError(f"{path}: unsupported image mode {mode}; expected 8-bit RGBA PNG")
            if mode not in ("RGBA", "LA") and not (mode == "P" and "transparency" in image.info):
                raise DatasetError(f"{path}: image has no alpha channel ({mode}); expected RGBA as in nerf_synthetic")
            pixels = np.asarray(image.convert("RGBA"))
    except UnidentifiedImageError:
        raise DatasetError(f"{path}: not an image Pillow can read; expected an 8-bit RGBA PNG") from None
    except Image.DecompressionBombError as exc:
        raise DatasetError(f"{path}: image is too large ({_one_line(exc)})") from None
    except (OSError, SyntaxError, ValueError, EOFError, zlib.error, struct.error) as exc:
        # Pillow's damaged-file errors: "image file is truncated", "broken PNG file"...
        raise DatasetError(f"{path}: cannot read image ({_one_line(exc) or type(exc).__name__})") from None
    if pixels.ndim != 3 or pixels.shape[2] != 4 or pixels.dtype != np.uint8 or 0 in pixels.shape:
        raise DatasetError(f"{path}: cannot read image as 8-bit RGBA (got {pixels.dtype} {pixels.shape})")
    return pixels


def read_intrinsics(data: dict, path: Path, width: int, height: int) -> Intrinsics:
    """Exact intrinsics if the JSON has them, else the reference loaders' from
    ``camera_angle_x``; checked against the images' size. A ``camera_angle_x``, ``w`` or
    ``h`` present in the JSON must be valid even where the exact intrinsics make it unused."""
    for key, actual in (("w", width), ("h", height)):
        if key in data and _image_side(data, key, path) != actual:
            raise DatasetError(f"{path}: '{key}' is {_show(data[key])} but the images are {width}×{height}")
    angle = None
    if "camera_angle_x" in data or not all(key in data for key in ("fl_x", "fl_y", "cx", "cy")):
        angle = _finite_number(data, "camera_angle_x", path)
        if angle >= math.pi:
            raise DatasetError(f"{path}: 'camera_angle_x' = {angle} is not a field of view below π")
    if all(key in data for key in ("fl_x", "fl_y", "cx", "cy")):
        return Intrinsics(
            width, height,
            _finite_number(data, "fl_x", path), _finite_number(data, "fl_y", path),
            _finite_number(data, "cx", path, positive=False), _finite_number(data, "cy", path, positive=False),
        )
    if math.tan(0.5 * angle) == 0.0:  # a subnormal angle: its tangent underflows to zero
        raise DatasetError(f"{path}: 'camera_angle_x' = {angle} is too small a field of view")
    intrinsics = Intrinsics.from_camera_angle_x(width, height, angle)
    if not _in_range(intrinsics.fl_x):
        raise DatasetError(f"{path}: 'camera_angle_x' = {angle} is too small a field of view")
    return intrinsics


def _split_json(dataset_dir: Path, split: str) -> Path:
    if not split or any(c in split for c in "/\\\x00"):  # a name, not a path to another folder
        raise DatasetError(f"{dataset_dir}: {_show(split)} is not a split name (train, val, test...)")
    return dataset_dir / transforms_name(split)


def _read_images(paths: list[Path]) -> np.ndarray:
    """The images as one uint8 array ``[N, H, W, 4]``, filled image by image: no list of images
    beside a stacked copy, so loading peaks at the split's own size (100 views at 800×800:
    256 MB). Decoded on torch's threads (Pillow's decoder leaves the GIL): lego's 13 test views
    at 800×800 took 0.23-0.31 s on one of 2 AVX2 cores, 0.17-0.21 s on both. The first bad
    image in the split's order is the one reported."""
    first = _read_rgba(paths[0])  # its size is every image's
    images = np.empty((len(paths), *first.shape), np.uint8)
    images[0] = first

    def read_into(index: int) -> None:
        pixels = _read_rgba(paths[index])
        if pixels.shape != first.shape:
            raise DatasetError(f"{paths[index]}: size {pixels.shape[1]}×{pixels.shape[0]} differs from "
                               f"{paths[0].name}'s {first.shape[1]}×{first.shape[0]}")
        images[index] = pixels

    with ThreadPoolExecutor(max_workers=max(1, torch.get_num_threads())) as pool:
        for _ in pool.map(read_into, range(1, len(paths))):  # raises the first failure in order
            pass
    return images


def load_split(dataset_dir: Path | str, split: str) -> DatasetSplit:
    """Read ``transforms_{split}.json`` and its images."""
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise DatasetError(f"{dataset_dir}: dataset folder not found")
    json_path = _split_json(dataset_dir, split)
    data = _read_json(json_path)
    frames = _frames(data, json_path)
    # The JSON first, then the images: a JSON mistake is reported before any image is read.
    poses = [_pose(frame, index, json_path) for index, frame in enumerate(frames)]
    paths = [_image_path(dataset_dir, frame, index, json_path) for index, frame in enumerate(frames)]
    depth_paths = [_depth_path(dataset_dir, frame, index, json_path) for index, frame in enumerate(frames)]
    images = _read_images(paths)
    height, width = images.shape[1:3]
    return DatasetSplit(
        name=split,
        intrinsics=read_intrinsics(data, json_path, width, height),
        poses=torch.from_numpy(np.stack(poses)).float(),
        rgba=torch.from_numpy(images),
        image_paths=paths,
        depth_paths=depth_paths,
    )


def load_split_poses(dataset_dir: Path | str, split: str) -> Tensor:
    """The camera-to-world poses ``[N, 4, 4]`` of ``transforms_{split}.json``, without its
    images (what a bake needs: where the views were taken from)."""
    json_path = _split_json(Path(dataset_dir), split)
    frames = _frames(_read_json(json_path), json_path)
    return torch.from_numpy(np.stack([_pose(frame, index, json_path) for index, frame in enumerate(frames)])).float()


@dataclass
class StillCameras:
    """Cameras without images that share one set of intrinsics: what to render (e.g. the
    Blender add-on's active camera)."""

    intrinsics: Intrinsics
    poses: Tensor  # [N, 4, 4] camera-to-world
    stems: list[str]


def load_cameras(json_path: Path | str) -> StillCameras:
    """Cameras from a transforms JSON that needs no images: it must give the image size
    (``w``, ``h``) and the intrinsics; frames may name their output (``file_path``, whose
    stem names the render; two frames may not name the same one)."""
    json_path = Path(json_path)
    data = _read_json(json_path)
    frames = _frames(data, json_path)
    if "w" not in data or "h" not in data:
        raise DatasetError(f"{json_path}: a camera file needs the image size as whole numbers 'w' and 'h'")
    width, height = _image_side(data, "w", json_path), _image_side(data, "h", json_path)
    poses, stems, seen = [], [], {}
    for index, frame in enumerate(frames):
        poses.append(_pose(frame, index, json_path))
        name = frame.get("file_path")
        if name is None:
            stem = f"view_{index:03d}"
        elif not isinstance(name, str) or "\x00" in name or not PurePath(name).stem:
            raise DatasetError(f"{json_path}: frame {index} 'file_path' {_show(name)} is not a name for its render")
        else:
            stem = PurePath(name).stem
        if stem in seen:
            raise DatasetError(f"{json_path}: frames {seen[stem]} and {index} would both render to {stem}.png")
        seen[stem] = index
        stems.append(stem)
    return StillCameras(read_intrinsics(data, json_path, width, height), torch.from_numpy(np.stack(poses)).float(), stems)


@dataclass
class AnimationFrame:
    frame: int  # Blender's frame number
    stem: str  # the file name of its images
    intrinsics: Intrinsics  # this frame's own (the lens may be animated)
    pose: Tensor  # [4, 4] camera-to-world in the NeRF frame
    cycles_path: Path | None  # Cycles' render of the frame, when one was asked for


@dataclass
class CameraAnimation:
    """A camera path written by datasets_gen (``--camera-path``) or the add-on: per frame a
    pose and exact intrinsics, one image size, and the scene's frame rate."""

    path: Path
    camera: str
    fps: float
    frames: list[AnimationFrame]

    @property
    def size(self) -> tuple[int, int]:
        return self.frames[0].intrinsics.width, self.frames[0].intrinsics.height


def load_camera_animation(json_path: Path | str) -> CameraAnimation:
    """A camera-path JSON (``camera_path.json``): every problem is a DatasetError naming it."""
    json_path = Path(json_path)
    data = _read_json(json_path)
    frames = _frames(data, json_path)
    fps = _finite_number(data, "fps", json_path)
    result, seen = [], set()
    for index, entry in enumerate(frames):
        if not isinstance(entry, dict):
            raise DatasetError(f"{json_path}: frame {index} is not an object")
        number = entry.get("frame")
        if not isinstance(number, int) or isinstance(number, bool):
            raise DatasetError(f"{json_path}: frame {index} needs its frame number 'frame' as a whole number")
        stem = f"{number:04d}"
        if stem in seen:
            raise DatasetError(f"{json_path}: frame {number} is listed twice")
        seen.add(stem)
        where = f"{json_path} frame {number}"
        for key in ("w", "h", "fl_x", "fl_y", "cx", "cy"):
            if key not in entry:
                raise DatasetError(f"{where}: needs the intrinsics w, h, fl_x, fl_y, cx, cy (missing '{key}')")
        width, height = _image_side(entry, "w", json_path), _image_side(entry, "h", json_path)
        cycles = entry.get("cycles_file_path")
        if cycles is not None and (not isinstance(cycles, str) or not cycles):
            raise DatasetError(f"{where}: 'cycles_file_path' {_show(cycles)} is not a file name")
        result.append(AnimationFrame(
            number, stem, read_intrinsics(entry, json_path, width, height),
            torch.from_numpy(_pose(entry, index, json_path)).float(),
            _inside(json_path.parent, cycles, "cycles_file_path", index, json_path) if cycles else None))
    sizes = {(f.intrinsics.width, f.intrinsics.height) for f in result}
    if len(sizes) > 1:
        raise DatasetError(f"{json_path}: frames differ in size ({sorted(sizes)}); a video keeps one size")
    camera = data.get("camera")
    return CameraAnimation(json_path, camera if isinstance(camera, str) else json_path.parent.name, fps,
                           sorted(result, key=lambda f: f.frame))


def load_scene_profile(dataset_dir: Path | str) -> dict | None:
    """``scene_profile.json`` as written by datasets_gen, or None for other tools' datasets."""
    path = Path(dataset_dir) / PROFILE_NAME
    return _read_json(path) if path.exists() else None


def load_scene_bounds(dataset_dir: Path | str) -> SceneBounds | None:
    """The bounds from ``scene_profile.json``, or None when the dataset has none (datasets
    from other tools)."""
    profile = load_scene_profile(dataset_dir)
    if profile is None:
        return None
    path = Path(dataset_dir) / PROFILE_NAME
    bounds = profile.get("bounds")
    if not isinstance(bounds, dict):
        raise DatasetError(f"{path}: 'bounds' must be an object with 'min' and 'max', got {_show(bounds)}")
    corners = []
    for key in ("min", "max"):
        values = bounds.get(key)
        numbers = [_as_float(v) for v in values] if isinstance(values, list) else []
        if len(numbers) != 3 or any(n is None for n in numbers):
            raise DatasetError(f"{path}: 'bounds' '{key}' must be three numbers, got {_show(values)}")
        if not all(_in_range(n) for n in numbers):
            raise DatasetError(f"{path}: 'bounds' '{key}' must be three finite numbers, got {_show(values)}")
        corners.append(tuple(numbers))
    box_min, box_max = corners
    # Compared as the float32 the grids and ray bounds will hold them in.
    if any(not np.float32(lo) < np.float32(hi) for lo, hi in zip(box_min, box_max)):
        raise DatasetError(f"{path}: 'bounds' min {list(box_min)} is not below max {list(box_max)}")
    if any(not _in_range(hi - lo) for lo, hi in zip(box_min, box_max)):
        raise DatasetError(f"{path}: 'bounds' is too large to compute with in float32")
    return SceneBounds(box_min, box_max)  # type: ignore[arg-type]
