"""The dataset in other tools' layouts, written beside nerf_synthetic's from the same render.

- ``colmap``: a COLMAP model of the training views with their images and masks in ``colmap/``,
  and ``points3d.ply``: the scene's surface points (colmap_export; needs numpy).
- ``ngp``: one ``transforms.json`` as Instant-NGP and nerfstudio read it: the shared exact
  intrinsics (``fl_x, fl_y, cx, cy, w, h``, ``camera_angle_x/y``), ``aabb_scale``, and every
  frame of every split with its image's path (extension included) and camera-to-world matrix
  (the same OpenGL convention as nerf_synthetic's). nerfstudio takes the splits from
  ``train_filenames``, ``val_filenames`` and ``test_filenames``; Instant-NGP trains on every
  frame listed (give it ``transforms_train.json`` to hold the test views out).  With ``colmap``
  it names ``points3d.ply`` as ``ply_file_path``, nerfstudio's initial points for splatfacto.

Pure (standard library): the generator and ``--merge`` call ``write_formats`` with the split
documents they have just written.

Example:
    >>> frame = {"file_path": "./train/r_0", "transform_matrix": [[1, 0, 0, 0]] * 4}
    >>> split = {"fl_x": 10.0, "fl_y": 10.0, "cx": 4.0, "cy": 4.0, "w": 8, "h": 8, "camera_angle_x": 0.76,
    ...          "frames": [frame]}
    >>> document = ngp_document({"train": split}, {"bounds": {"min": [-1.2, -1, -1], "max": [1, 1, 1]}})
    >>> document["aabb_scale"], document["frames"][0]["file_path"], document["train_filenames"]
    (1, 'train/r_0.png', ['train/r_0.png'])
"""

from __future__ import annotations

import math
import os
import shutil
from typing import Any, Mapping

from nerf_contract.dataset_layout import COLMAP_DIR, NGP_NAME, POINTS_NAME

from .output_dir import write_json_atomic

#: Instant-NGP maps the NeRF frame into its unit cube by p * 0.33 + 0.5 (its defaults, which
#: nerf_synthetic scenes use); aabb_scale is the side of the cube rays march in, a power of 2.
NGP_SCALE = 0.33
MAX_AABB_SCALE = 128
INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")


def aabb_scale(bounds_min: list[float], bounds_max: list[float]) -> int:
    """The smallest power of 2 whose cube, centred on the origin of the NeRF frame at
    Instant-NGP's scale, holds the scene's bounds (1 to 128)."""
    reach = max(abs(value) for value in (*bounds_min, *bounds_max))
    needed = 2.0 * NGP_SCALE * reach
    return int(min(MAX_AABB_SCALE, 2 ** max(0, math.ceil(math.log2(needed))) if needed > 0 else 1))


def _image_path(file_path: str) -> str:
    path = file_path.removeprefix("./")
    return path if path.lower().endswith(".png") else path + ".png"


def ngp_document(documents: Mapping[str, dict], profile: Mapping[str, Any]) -> dict[str, Any]:
    """The single ``transforms.json`` of all splits (in train, val, test order)."""
    first = next(iter(documents.values()))
    document: dict[str, Any] = {key: first[key] for key in INTRINSIC_KEYS if key in first}
    bounds = profile.get("bounds") or {}
    document["aabb_scale"] = aabb_scale(bounds["min"], bounds["max"]) if bounds.get("min") else 1
    document["aabb_scale_rule"] = (f"the smallest power of 2 holding the scene's bounds at Instant-NGP's scale "
                                   f"{NGP_SCALE} (scene_profile.json bounds)")
    if "world_to_nerf" in first:
        document["world_to_nerf"] = first["world_to_nerf"]
    frames = []
    for split, split_document in documents.items():
        names = []
        for frame in split_document["frames"]:
            name = _image_path(frame["file_path"])
            names.append(name)
            frames.append({"file_path": name, "transform_matrix": frame["transform_matrix"]})
        document[f"{split}_filenames"] = names
    document["frames"] = frames
    return document


#: What each layout writes into the dataset's folder.
OUTPUTS = {"colmap": (COLMAP_DIR, POINTS_NAME), "ngp": (NGP_NAME,)}


def write_formats(out_dir: str, formats: tuple[str, ...] | list[str], documents: Mapping[str, dict],
                  profile: Mapping[str, Any], progress: bool = True) -> None:
    """Write each of ``formats`` (besides nerf_synthetic's, already written) into ``out_dir``,
    and remove the files of the others: an earlier run's layout would describe other renders."""
    for name, outputs in OUTPUTS.items():
        if name not in formats:
            for output in outputs:
                path = os.path.join(out_dir, output)
                if os.path.isdir(path):
                    shutil.rmtree(path)
                elif os.path.isfile(path):
                    os.remove(path)
    if "colmap" in formats:
        from .colmap_export import write_colmap  # numpy, which Debian's Blender lacks

        write_colmap(out_dir, documents, profile, progress)
    if "ngp" in formats:
        document = ngp_document(documents, profile)
        if "colmap" in formats:
            document["ply_file_path"] = POINTS_NAME
        write_json_atomic(os.path.join(out_dir, NGP_NAME), document)
