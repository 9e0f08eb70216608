"""Where a run's test error lies, by what the true surface under each pixel is made of: each
test pixel's ground-truth depth gives the point it sees, the dataset's occupancy prior gives
that point's region (``regions`` in ``occupancy_prior.npz``: diffuse, glossy, metal, thin film,
transmissive), and pixels whose alpha is between 0.02 and 0.98 count as edges. For each region:
its share of the pixels, its share of the squared error, and the PSNR the views would score if
that region's error were zero (how much any change to that region's appearance could gain).

    python tools/error_by_region.py DATASET RENDERS [--noise-from OTHER]

RENDERS holds the test views' renders by name (``RUN/renders/test`` after ``render RUN``). The
PSNR here is the mean squared error's over every pixel of every view, on white, as `eval`
composites; `eval`'s own figure is the mean of each view's PSNR, a few hundredths away.

With ``--noise-from OTHER``, a dataset of the same scene and test cameras rendered with another
Cycles seed (``datasets_gen ... --seed 1``: the test views do not depend on it), the ground
truth's own noise is measured too: half the squared difference of the two renders is one
render's variance about the noise-free image, so it is the error a perfect model would make.
Each region's share of its error that is the ground truth's noise is printed beside it, and the
PSNR a perfect model would score.

With ``--bright T``, each material's pixels whose ground truth is brighter than T in some
channel (on a dark glossy surface: a light's highlight) are counted apart from its others."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from nerf_backend.core.cameras import camera_rays, pixel_centres
from nerf_backend.core.files import read_exr
from nerf_backend.data.dataset import load_split
from nerf_backend.data.occupancy_prior import load_occupancy_prior
from nerf_backend.evaluation.evaluate import read_rgb
from nerf_contract.dataset_layout import APPEARANCE_REGIONS

EDGE_ALPHA = (0.02, 0.98)
BACKGROUND, EDGE = -1, -2
BRIGHT = 100  # added to a material's label where its ground truth is bright (--bright)


def split_bright(labels: np.ndarray, truth: np.ndarray, threshold: float | None) -> np.ndarray:
    """``labels`` with each material's pixels brighter than ``threshold`` (any channel of
    ``truth [..., 3]``) moved to label + BRIGHT; edges and background kept.

    Example:
        >>> split_bright(np.array([2, 2, EDGE]), np.array([[0.9, 0.1, 0.1], [0.2] * 3, [1.0] * 3]), 0.5).tolist()
        [102, 2, -2]
    """
    if threshold is None:
        return labels
    return np.where((labels >= 0) & (truth.max(axis=-1) > threshold), labels + BRIGHT, labels)


def nearest_region(regions: np.ndarray) -> np.ndarray:
    """Every cell given the region of the nearest classified cell (the prior marks cells around
    the surface; a point the depth gives may fall just outside them)."""
    _, nearest = ndimage.distance_transform_edt(regions == 0, return_indices=True)
    return regions[tuple(nearest)]


def pixel_regions(split, index: int, regions: np.ndarray, box_min: np.ndarray, cell: float) -> np.ndarray:
    """``[H·W]``: each pixel's region index, BACKGROUND or EDGE."""
    depth = read_exr(split.depth_path(index))
    alpha = depth["A"].reshape(-1)
    height, width = depth["Z"].shape
    origins, directions = camera_rays(split.intrinsics, split.poses[index], pixel_centres(width, torch.arange(height * width)))
    points = (origins + directions * torch.from_numpy(depth["Z"].reshape(-1).astype(np.float32))[:, None]).numpy()
    cells = np.floor((points - box_min) / cell).astype(np.int64)
    inside = ((cells >= 0) & (cells < np.asarray(regions.shape))).all(axis=1)
    cells = np.clip(cells, 0, np.asarray(regions.shape) - 1)
    found = np.where(inside & (alpha > 0.5), regions[cells[:, 0], cells[:, 1], cells[:, 2]].astype(np.int64), BACKGROUND)
    return np.where((alpha > EDGE_ALPHA[0]) & (alpha < EDGE_ALPHA[1]), EDGE, found)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("renders", type=Path)
    parser.add_argument("--noise-from", type=Path, help="the same test views rendered with another Cycles seed")
    parser.add_argument("--bright", type=float, help="count each material's pixels brighter than this apart")
    args = parser.parse_args()
    split = load_split(args.dataset, "test")
    other = load_split(args.noise_from, "test") if args.noise_from else None
    if other is not None and (len(other) != len(split) or not torch.equal(other.poses, split.poses)):
        raise SystemExit(f"{args.noise_from}: its test cameras are not {args.dataset}'s")
    prior = load_occupancy_prior(args.dataset, "surface")
    if prior is None or prior.regions is None:
        raise SystemExit(f"{args.dataset}: no occupancy prior with regions (a dataset made by datasets_gen since issue 60)")
    regions = nearest_region(prior.regions.numpy())
    error_sum: dict[int, float] = {}
    noise_sum: dict[int, float] = {}
    pixel_count: dict[int, int] = {}
    total, pixels = 0.0, 0
    for index in range(len(split)):
        if split.depth_path(index) is None:
            raise SystemExit(f"{args.dataset}: test view {index} has no ground-truth depth")
        truth = split.rgb_on_white(index).numpy().astype(np.float64)
        render = read_rgb(args.renders / f"{split.image_paths[index].stem}.png").astype(np.float64)
        error = ((render - truth) ** 2).sum(axis=-1).reshape(-1)
        labels = split_bright(pixel_regions(split, index, regions, np.asarray(prior.box_min), prior.cell_size),
                              truth.reshape(-1, 3), args.bright)
        if other is not None:
            noise = ((other.rgb_on_white(index).numpy().astype(np.float64) - truth) ** 2).sum(axis=-1).reshape(-1) / 2
        for label in np.unique(labels):
            chosen = labels == label
            error_sum[int(label)] = error_sum.get(int(label), 0.0) + float(error[chosen].sum())
            if other is not None:
                noise_sum[int(label)] = noise_sum.get(int(label), 0.0) + float(noise[chosen].sum())
            pixel_count[int(label)] = pixel_count.get(int(label), 0) + int(chosen.sum())
        total += float(error.sum())
        pixels += error.size
    psnr = -10 * math.log10(total / (3 * pixels))
    print(f"PSNR {psnr:.2f} dB over {len(split)} test views")
    if noise_sum:
        print(f"a perfect model (the ground truth's noise alone): PSNR {-10 * math.log10(sum(noise_sum.values()) / (3 * pixels)):.2f} dB")
    names = {BACKGROUND: "background", EDGE: f"edges ({EDGE_ALPHA[0]} < alpha < {EDGE_ALPHA[1]})"}
    for label in sorted(error_sum):
        without = -10 * math.log10(max(total - error_sum[label], 1e-30) / (3 * pixels))
        noise = f"  of it noise {noise_sum[label] / max(error_sum[label], 1e-30):5.0%}" if noise_sum else ""
        name = names.get(label) or (f"{APPEARANCE_REGIONS[label - BRIGHT]}, bright" if label >= BRIGHT
                                    else APPEARANCE_REGIONS[label])
        print(f"{name:30s} pixels {pixel_count[label] / pixels:6.1%}  "
              f"error {error_sum[label] / total:6.1%}  PSNR were it zero {without:.2f} (+{without - psnr:.2f}){noise}")


if __name__ == "__main__":
    main()
