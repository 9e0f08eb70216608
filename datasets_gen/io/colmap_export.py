"""``--format colmap``: the dataset's training views as a COLMAP model with images and masks, and
the scene's surface points as the initial point cloud of Gaussian-splatting trainers.

Written beside nerf_synthetic's files, from the same render:

- ``colmap/sparse/0/{cameras,images,points3D}.{txt,bin}``: PINHOLE cameras (one per distinct
  intrinsics), each training view's exact pose, and ``POINT_SAMPLES`` points sampled on the
  scene's true surface (``scene_geometry.ply``), kept when at least one view sees them, with their
  tracks and rendered colours (colmap_model).
- ``colmap/images/r_K.png``: the render composited on the protocol's white background (RGB, as
  every COLMAP-reading trainer loads images), and ``colmap/masks/r_K.png``: its alpha (8-bit).
- ``points3d.ply`` at the dataset's root: the same points (x y z nx ny nz red green blue), which
  the original 3DGS code reads beside ``transforms_train.json`` instead of a random cloud.

Why a ``colmap/`` folder and only the training views: 3DGS reads any folder holding ``sparse/``
as COLMAP and then holds out every 8th image by name, so a model at the root would hide the
nerf_synthetic layout (and its exact train/test split) from it, and test views in the model
would be trained on.  The test views stay in ``transforms_test.json`` (and ``transforms.json``).

The folder is built under a hidden temporary name and moved into place whole.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from typing import Any, Mapping

import numpy as np

from nerf_contract.dataset_layout import COLMAP_DIR, GEOMETRY_NAME, POINTS_NAME

from ..core.options import DatasetGenError
from ..core.progress import ViewProgress
from ..core.zbuffer import PinholeCamera, depth_buffer
from .colmap_model import (
    TrackBuilder,
    cameras_binary,
    cameras_text,
    images_binary,
    images_text,
    points3d_binary,
    points3d_text,
    points_ply_bytes,
    sample_surface,
    world_to_camera,
)
from .output_dir import write_file_atomic
from .png_image import png_bytes, read_png
from .surface_mesh import FRAME, read_ply

#: Surface points drawn (uniform by area); those no training view sees are dropped.
POINT_SAMPLES = 20_000
SPLIT = "train"
_PARTIAL = ".colmap-partial-"


def write_colmap(out_dir: str, documents: Mapping[str, dict], profile: Mapping[str, Any],
                 progress: bool = True) -> dict[str, Any]:
    """Write the COLMAP model, its images and masks, and points3d.ply; return a summary."""
    started = time.perf_counter()
    if not isinstance(profile.get("geometry"), dict):
        raise DatasetGenError(f"--format colmap: {out_dir} has no scene geometry to sample points from "
                              f"({profile.get('geometry_reason', 'none was written')})")
    geometry_path = os.path.join(out_dir, GEOMETRY_NAME)
    try:
        vertices, faces = read_ply(geometry_path)
    except (OSError, ValueError) as error:
        raise DatasetGenError(f"--format colmap: cannot read {geometry_path}: {error}") from None
    document = documents[SPLIT]
    seed = int(document.get("generator", {}).get("settings", {}).get("seed", 0))
    points, normals = sample_surface(vertices, faces, POINT_SAMPLES, seed)
    builder = TrackBuilder(points, normals)
    cameras: dict[PinholeCamera, int] = {}

    for name in os.listdir(out_dir):  # an interrupted export's leftovers
        if name.startswith(_PARTIAL):
            shutil.rmtree(os.path.join(out_dir, name), ignore_errors=True)
    staging = tempfile.mkdtemp(prefix=_PARTIAL, dir=out_dir)
    try:
        for folder in ("sparse/0", "images", "masks"):
            os.makedirs(os.path.join(staging, folder))
        frames = document["frames"]
        with ViewProgress(len(frames), enabled=progress, desc="COLMAP") as bar:
            for image_id, frame in enumerate(frames, start=1):
                camera = _camera(document, frame)
                camera_id = cameras.setdefault(camera, len(cameras) + 1)
                rotation, translation = world_to_camera(frame["transform_matrix"])
                stem = frame["file_path"].removeprefix("./").removesuffix(".png")
                rgb, alpha = _composite(os.path.join(out_dir, stem + ".png"), camera)
                image_name = os.path.basename(stem) + ".png"
                _write(os.path.join(staging, "images", image_name), png_bytes(rgb))
                _write(os.path.join(staging, "masks", image_name), png_bytes(alpha))
                depth = depth_buffer(vertices, faces, rotation, translation, camera)
                builder.add_view(image_id, camera_id, image_name, rotation, translation, camera, depth, rgb)
                bar.advance_named(image_name)
        model = builder.model({camera_id: camera for camera, camera_id in cameras.items()})
        sparse = os.path.join(staging, "sparse", "0")
        for name, content in (("cameras.txt", cameras_text(model)), ("images.txt", images_text(model)),
                              ("points3D.txt", points3d_text(model))):
            _write(os.path.join(sparse, name), content.encode("utf-8"))
        for name, content in (("cameras.bin", cameras_binary(model)), ("images.bin", images_binary(model)),
                              ("points3D.bin", points3d_binary(model))):
            _write(os.path.join(sparse, name), content)
        _replace_folder(staging, os.path.join(out_dir, COLMAP_DIR))
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    ply = points_ply_bytes(model.xyz, model.normals, model.rgb,
                           f"surface points seen by the training views, {FRAME}")
    write_file_atomic(os.path.join(out_dir, POINTS_NAME), lambda handle: handle.write(ply))
    summary = {"images": len(model.images), "cameras": len(model.cameras), "points": len(model.point_ids),
               "sampled": POINT_SAMPLES, "mean_track_length": model.mean_track_length(),
               "seconds": time.perf_counter() - started}
    print(f"datasets_gen: COLMAP model: {summary['images']} images, {summary['points']} of {POINT_SAMPLES} "
          f"surface points seen (mean track {summary['mean_track_length']:.1f} views), "
          f"{summary['seconds']:.1f} s", file=sys.stderr)
    return summary


def _camera(document: Mapping[str, Any], frame: Mapping[str, Any]) -> PinholeCamera:
    """A frame's exact intrinsics (its own keys, else its split's)."""
    def value(key: str) -> Any:
        return frame.get(key, document[key])
    return PinholeCamera(int(value("w")), int(value("h")), float(value("fl_x")), float(value("fl_y")),
                         float(value("cx")), float(value("cy")))


def _composite(path: str, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """(RGB on white, alpha) of a render, both uint8."""
    try:
        rgba = read_png(path)
    except (OSError, ValueError) as error:
        raise DatasetGenError(f"--format colmap: cannot read the render {path}: {error}") from None
    if rgba.shape != (camera.height, camera.width, 4):
        raise DatasetGenError(f"--format colmap: {path} is {rgba.shape[1]}x{rgba.shape[0]} with {rgba.shape[2]} "
                              f"channels, expected {camera.width}x{camera.height} RGBA")
    # round(c a / 255 + 255 (1 - a / 255)) in integers (never a tie: 255 is odd).
    alpha = rgba[..., 3:].astype(np.uint32)
    rgb = (rgba[..., :3] * alpha + 255 * (255 - alpha) + 127) // 255
    return rgb.astype(np.uint8), rgba[..., 3]


def _write(path: str, content: bytes) -> None:
    with open(path, "wb") as handle:
        handle.write(content)


def _replace_folder(staging: str, final: str) -> None:
    """Move the finished folder into place; an earlier export's is removed only after."""
    old = None
    if os.path.exists(final):
        old = tempfile.mkdtemp(prefix=_PARTIAL, dir=os.path.dirname(final))
        os.replace(final, os.path.join(old, "previous"))
    os.replace(staging, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
