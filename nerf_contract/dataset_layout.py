"""A dataset's folder, as ``datasets_gen`` writes it and the backend and the add-on read it
(nerf_synthetic's layout, with the generator's extras beside it)::

    DATASET/transforms_{train,val,test}.json   cameras and frames of each split
    DATASET/{train,val,test}/r_K.png           the views (r_K_depth.exr, r_K_normal.exr on request)
    DATASET/scene_profile.json                 what Blender knows of the scene
    DATASET/occupancy_prior.npz                its voxelised geometry (named in the profile)
    DATASET/scene_geometry.ply                 its renderable triangles (named in the profile)
    DATASET/transforms.json                    every split, Instant-NGP's and nerfstudio's layout
    DATASET/colmap/, DATASET/points3d.ply       a COLMAP model of the training views, surface points
    DATASET/camera_paths/CAMERA/camera_path.json   an animated camera; cycles/ its Cycles frames

Example:
    >>> transforms_name("val"), view_names(3)["png"], camera_path_folder("cam.001 (left)")
    ('transforms_val.json', 'r_3.png', 'camera_paths/cam.001_left')
"""

from __future__ import annotations

import re

SPLITS = ("train", "val", "test")
PROFILE_NAME = "scene_profile.json"
PRIOR_NAME = "occupancy_prior.npz"
# What the surface in each cell of the prior's ``regions`` array is made of, by index (0: no
# surface there, or none classified), from the scene's materials (the profile's ``materials``,
# each with its ``region`` and why). Ordered by how much a surface's colour changes with the
# view: where regions share a cell, the later one is kept.
APPEARANCE_REGIONS = ("none", "diffuse", "glossy", "metal", "thin_film", "transmissive")
# The profile's ``world`` ``kind`` for a world of one colour (its ``color`` and ``strength`` beside
# it): the light the backend's bent rays start seeing through glass.
WORLD_UNIFORM = "uniform colour"
GEOMETRY_NAME = "scene_geometry.ply"
NGP_NAME = "transforms.json"
COLMAP_DIR = "colmap"
POINTS_NAME = "points3d.ply"
CAMERA_PATHS_DIR = "camera_paths"
CAMERA_PATH_NAME = "camera_path.json"
CYCLES_FRAMES_DIR = "cycles"
VIEW_PNG_GLOB = "r_*.png"  # every view's image in a split's folder


def transforms_name(split: str) -> str:
    """The split's JSON document: ``transforms_{split}.json``."""
    return f"transforms_{split}.json"


def view_names(index: int) -> dict[str, str]:
    """A view's file names inside its split's folder: ``png``, ``depth``, ``normal``."""
    return {"png": f"r_{index}.png", "depth": f"r_{index}_depth.exr", "normal": f"r_{index}_normal.exr"}


def safe_name(name: str) -> str:
    """A camera's name as a folder name: letters, digits, ``-``, ``_`` and ``.`` kept."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "camera"


def camera_path_folder(camera_name: str) -> str:
    """Where a camera's path lives, relative to the dataset: ``camera_paths/SAFE_NAME``."""
    return f"{CAMERA_PATHS_DIR}/{safe_name(camera_name)}"
