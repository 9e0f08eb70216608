"""Does a mesh lie inside the dataset's silhouettes, and fill them? Points sampled uniformly on
the surface are projected into the training views and compared with Cycles' alpha (the
silhouette the images show):

- on background: the share of the mesh's points that land on transparent pixels, and how far
  (pixels) from the nearest opaque one: a mesh larger than the object, or floaters;
- uncovered: the share of opaque pixels farther than 1 and 2 pixels from any projected point:
  a mesh smaller than the object.

    python tools/silhouette_check.py DATASET [MESH.ply ...] [--views 10]

The dataset's own ``scene_geometry.ply`` (the truth, in the NeRF frame) is checked first, as the
yardstick; each MESH is a ``mesh`` command's output (Blender's world frame, moved into the NeRF
frame with the dataset's ``world_to_nerf``). Every opaque pixel has a surface point within a
pixel when 3 million points are spread over the object; fewer points leave gaps the uncovered
share would count.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nerf_backend.core.cameras import project_points  # noqa: E402
from nerf_backend.core.ply import read_ply  # noqa: E402
from nerf_backend.data.dataset import load_split  # noqa: E402
from nerf_backend.metrics.geometry import sample_surface  # noqa: E402

POINTS = 3_000_000


def pixels(points: np.ndarray, camera_to_world: torch.Tensor, intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """The pixel (column, row) each point falls in, and which fall inside the image (every
    camera of a protocol dataset sees the whole object from outside it)."""
    where = project_points(intrinsics, camera_to_world.double(), torch.from_numpy(points)).floor().long().numpy()
    inside = (where[:, 0] >= 0) & (where[:, 0] < intrinsics.width) & (where[:, 1] >= 0) & (where[:, 1] < intrinsics.height)
    return where, inside


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("meshes", type=Path, nargs="*")
    parser.add_argument("--views", type=int, default=10, help="training views to check, evenly spread")
    args = parser.parse_args()
    split = load_split(args.dataset, "train")
    intrinsics = split.intrinsics
    frame = json.loads((args.dataset / "transforms_train.json").read_text()).get("world_to_nerf")
    views = list(range(0, len(split), max(1, len(split) // args.views)))[:args.views]
    opaque = {view: split.rgba[view, ..., 3].numpy() > 127 for view in views}
    to_opaque = {view: ndimage.distance_transform_edt(~mask) for view, mask in opaque.items()}
    for name, path in [("truth", args.dataset / "scene_geometry.ply"), *((str(m), m) for m in args.meshes)]:
        vertices, faces = read_ply(path)
        vertices = np.asarray(vertices, np.float64)
        if name != "truth" and frame:  # the mesh command writes Blender's world frame
            vertices = vertices * frame["scale"] + np.asarray(frame["translation"])
        points, _ = sample_surface(vertices, np.asarray(faces), POINTS, np.random.default_rng(0))
        off, uncovered_1, uncovered_2, opaque_pixels = [], 0, 0, 0
        for view in views:
            where, inside = pixels(points, split.poses[view], intrinsics)
            column, row = where[:, 0], where[:, 1]
            column, row = column[inside], row[inside]
            off.append(to_opaque[view][row, column])
            hit = np.zeros_like(opaque[view])
            hit[row, column] = True
            to_hit = ndimage.distance_transform_edt(~hit)
            uncovered_1 += int((opaque[view] & (to_hit > 1)).sum())
            uncovered_2 += int((opaque[view] & (to_hit > 2)).sum())
            opaque_pixels += int(opaque[view].sum())
        off = np.concatenate(off)
        print(f"{name}: on background {np.mean(off > 0):.4f} of the points (beyond 1 px {np.mean(off > 1):.4f}, "
              f"2 px {np.mean(off > 2):.4f}); uncovered {uncovered_1 / opaque_pixels:.4f} of the opaque pixels "
              f"beyond 1 px, {uncovered_2 / opaque_pixels:.4f} beyond 2 px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
