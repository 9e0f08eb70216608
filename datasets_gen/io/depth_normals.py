"""Depth and normal images of a view, from Blender's render passes to the dataset's layout.

Layout (the backend writes its own renders the same way):

* ``r_{i}_depth.exr``: float32 channels ``Z`` = distance from the camera centre along the
  pixel's ray, in NeRF-frame units, and ``A`` = alpha (coverage, 0 on the background);
  background pixels hold Z = 0 and A = 0.
* ``r_{i}_normal.exr``: float32 channels ``X``, ``Y``, ``Z`` = world-space unit normal in the
  NeRF frame (the frame only scales and translates, so Blender's world normals are kept),
  zeros on the background.

Cycles' depth pass is planar (along the optical axis), taken from each pixel's first sample,
with 1e10 where that sample hit nothing.  The generator therefore reads depth and normals from
a one-sample render whose pixel filter is 0.01 px wide (the sample is the ray through the pixel
centre) and alpha from the beauty render.  Here planar depth becomes the distance along that
ray (``intrinsics.ray_length_factors``) times the frame's scale, normals are renormalised, and
every pixel without coverage, or whose centre ray hits nothing, gets Z = 0.

Standard library only, like the rest of the generator's run-time code.
"""

from __future__ import annotations

import math
from array import array
from typing import Sequence

from .exr import write_float_channels

#: Cycles writes this (1e10) where the depth sample missed; anything beyond is "no surface".
MISS_DEPTH = 1.0e9

DEPTH_CHANNELS = ("A", "Z")
NORMAL_CHANNELS = ("X", "Y", "Z")

LAYOUT_RECORD = {
    "depth": {
        "file": "r_{i}_depth.exr",
        "channels": {
            "Z": "float32 distance from the camera centre along the pixel's ray (through the pixel centre), "
                 "NeRF-frame units",
            "A": "float32 alpha (coverage) of the rendered view, 0 on the background",
        },
    },
    "normal": {
        "file": "r_{i}_normal.exr",
        "channels": {"X": "float32", "Y": "float32", "Z": "float32"},
        "meaning": "world-space unit normal in the NeRF frame (same as Blender's world: the frame only scales "
                   "and translates)",
    },
    "background": "Z = 0 and A = 0 in the depth file, X = Y = Z = 0 in the normal file",
    "depth_sample": "the ray through the pixel centre (a one-sample render with a 0.01 px filter); Z = 0 also "
                    "where that ray misses the geometry although A > 0 (edge pixels)",
    "rows": "top to bottom, as the PNG; pixel centres at i + 0.5",
    "format": "OpenEXR, single part, scanline, ZIP compression",
}


def depth_channels(
    alpha: Sequence[float], planar_depth: Sequence[float], factors: Sequence[float], scale: float
) -> dict[str, "array[float]"]:
    """The depth file's channels: Z (ray distance x scale, 0 where nothing was hit) and A."""
    z = array(
        "f",
        [
            d * f * scale if (a > 0.0 and d < MISS_DEPTH) else 0.0
            for a, d, f in zip(alpha, planar_depth, factors)
        ],
    )
    return {"Z": z, "A": array("f", alpha)}


def normal_channels(
    alpha: Sequence[float], x: Sequence[float], y: Sequence[float], z: Sequence[float]
) -> dict[str, "array[float]"]:
    """The normal file's channels: unit vectors where covered and non-zero, zeros elsewhere."""
    out_x, out_y, out_z = array("f"), array("f"), array("f")
    for a, nx, ny, nz in zip(alpha, x, y, z):
        length = math.sqrt(nx * nx + ny * ny + nz * nz)
        if a > 0.0 and length > 1e-6:
            out_x.append(nx / length)
            out_y.append(ny / length)
            out_z.append(nz / length)
        else:
            out_x.append(0.0)
            out_y.append(0.0)
            out_z.append(0.0)
    return {"X": out_x, "Y": out_y, "Z": out_z}


def write_depth_normals(
    depth_path: str,
    normal_path: str,
    width: int,
    height: int,
    passes: dict[str, Sequence[float]],
    factors: Sequence[float],
    scale: float,
) -> None:
    """Write both files from the passes {"alpha", "depth", "normal_x", "normal_y", "normal_z"}."""
    alpha = passes["alpha"]
    write_float_channels(depth_path, width, height, depth_channels(alpha, passes["depth"], factors, scale))
    write_float_channels(
        normal_path, width, height,
        normal_channels(alpha, passes["normal_x"], passes["normal_y"], passes["normal_z"]),
    )
