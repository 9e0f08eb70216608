"""Coarse-to-fine images (data/image_pyramid.py): while a grid is still coarse, its rays come
from the training images downsampled to its cells; each coarse pixel is its block's mean and
its ray the block's middle ray; the full size once the grid holds its final detail."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import run_python
from nerf_backend.core.cameras import Intrinsics, camera_rays, pixel_centres
from nerf_backend.data.dataset import composite
from nerf_backend.data.image_pyramid import ImagePyramid, block_intrinsics, downsample_rgba, level_factor


def _random_rgba(count: int, height: int, width: int, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    rgba = torch.randint(0, 256, (count, height, width, 4), generator=generator, dtype=torch.uint8)
    rgba[..., 3][rgba[..., 3] < 64] = 0  # fully transparent pixels, as on a transparent film
    return rgba


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_a_coarse_pixel_composites_as_the_mean_of_its_block(factor):
    """Over any background, the downsampled pixel composited equals the mean of its block's
    pixels composited, to uint8 rounding (half a level of colour and of alpha, divided
    through α where α is small)."""
    rgba = _random_rgba(3, 8 * 4 + 3, 8 * 5 + 1)  # a remainder the blocks leave out
    coarse = downsample_rgba(rgba, factor)
    rows, cols = rgba.shape[1] // factor, rgba.shape[2] // factor
    assert coarse.shape == (3, rows, cols, 4) and coarse.dtype == torch.uint8
    for background in (0.0, 1.0, torch.tensor([0.2, 0.9, 0.5])):
        blocks = composite(rgba[:, :rows * factor, :cols * factor], background)
        expected = blocks.view(3, rows, factor, cols, factor, 3).mean(dim=(2, 4))
        # Colour is stored un-premultiplied: its rounding error (0.5/255) is scaled by α ≤ 1,
        # and alpha's rounding (0.5/255) moves the mix by at most that much again.
        assert (composite(coarse, background) - expected).abs().max() <= 1.0 / 255 + 1e-6


def test_a_fully_transparent_block_stays_transparent_and_an_opaque_one_keeps_its_mean():
    rgba = torch.zeros((1, 4, 4, 4), dtype=torch.uint8)
    rgba[0, :2, :2] = torch.tensor([10, 20, 30, 255], dtype=torch.uint8)
    rgba[0, :2, :2, 0] = torch.tensor([[10, 30], [50, 70]], dtype=torch.uint8)
    coarse = downsample_rgba(rgba, 2)
    assert coarse[0, 0, 0].tolist() == [40, 20, 30, 255]
    assert coarse[0, 1, 1].tolist() == [0, 0, 0, 0]


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_the_ray_through_a_coarse_pixel_is_its_blocks_middle_ray(factor):
    """Pixel i of the coarse image covers full-size pixels [k·i, k·i + k): its ray is the one
    through the full-size point k·(i + 0.5), for a shifted, non-square camera too."""
    full = Intrinsics(803, 600, 1111.0, 1020.0, 390.25, 311.5)
    coarse = block_intrinsics(full, factor)
    assert (coarse.width, coarse.height) == (803 // factor, 600 // factor)
    pose = torch.tensor([[0.6, -0.8, 0.0, 1.0], [0.8, 0.6, 0.0, -2.0], [0.0, 0.0, 1.0, 4.0], [0, 0, 0, 1]])
    index = torch.arange(coarse.width * coarse.height)
    origins, directions = camera_rays(coarse, pose, pixel_centres(coarse.width, index))
    origins_full, directions_full = camera_rays(full, pose, pixel_centres(coarse.width, index) * factor)
    assert torch.allclose(directions, directions_full, atol=1e-6) and torch.equal(origins, origins_full)


def test_the_level_follows_the_detail_down_to_the_smallest_size():
    pixel = 0.0036  # a full-size pixel of an 800×800 protocol view at the scene's centre
    assert level_factor(pixel, None, 800, 800) == 1
    assert level_factor(pixel, 0.5 * pixel, 800, 800) == 1  # finer than a pixel
    assert level_factor(pixel, 2.5 * pixel, 800, 800) == 2
    assert level_factor(pixel, 7.9 * pixel, 800, 800) == 4
    assert level_factor(pixel, 1000 * pixel, 800, 800) == 8  # 100 pixels: no smaller
    assert level_factor(pixel, 1000 * pixel, 800, 120) == 1  # 60 pixels would be too few
    assert level_factor(pixel, 1000 * pixel, 100, 100) == 1


def test_the_pyramid_makes_each_level_once_and_lets_them_go_at_full_size():
    rgba = _random_rgba(2, 16, 16)
    pyramid = ImagePyramid(rgba, Intrinsics(16, 16, 20.0, 20.0, 8.0, 8.0))
    quarter = pyramid.level(4)
    assert pyramid.level(4) is quarter and quarter.rgba.shape == (2, 4, 4, 4)
    assert pyramid.level(1).rgba is rgba and not pyramid._levels


def _upscaled(dataset: Path, out: Path, factor: int) -> Path:
    """``dataset`` with every image enlarged ``factor`` times (nearest) and its intrinsics
    scaled to match: the same scene at a size the pyramid downsamples."""
    shutil.copytree(dataset, out)
    for split in ("train", "val", "test"):
        path = out / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
            meta[key] = meta[key] * factor
        for frame in meta["frames"]:
            image = out / (frame["file_path"] + ".png")
            with Image.open(image) as opened:
                opened.resize((opened.width * factor, opened.height * factor), Image.NEAREST).save(image)
        path.write_text(json.dumps(meta))
    return out


def _image_sizes(run: Path) -> list[tuple[int, int]]:
    events = [json.loads(line) for line in (run / "events.jsonl").read_text().splitlines()]
    return [tuple(e["image_size"]) for e in events if e["event"] == "train"]


def test_training_starts_on_downsampled_images_and_ends_on_the_full_size(tiny_demo_dataset, tmp_path):
    """The tiny demo at 160×160 (a pixel 0.0177 units at the scene's centre): fast's
    48-vertex grid (cells of 2.2 pixels) starts on 80×80 images (40×40 would be under the
    smallest level's 64 pixels); from its first growth at step 10 (67 vertices, cells of 1.6
    pixels) it trains on the full size. Without coarse_images (the presets' default, chosen
    by bench: see the README) every step is full size."""
    dataset = _upscaled(tiny_demo_dataset, tmp_path / "dataset160", 4)
    common = ("--preset", "fast", "--iters", "40", "--no-progress", "--set", "grid.upsample_iterations=[10,20,30]",
              "--set", "validate_every=1000")
    run_python("-m", "nerf_backend", "train", str(dataset), "--out", str(tmp_path / "coarse"), *common,
               "--set", "coarse_images=true")
    # Logged every 10 steps: step 10's rays were drawn before that step's growth.
    assert _image_sizes(tmp_path / "coarse") == [(80, 80), (160, 160), (160, 160), (160, 160)]
    run_python("-m", "nerf_backend", "train", str(dataset), "--out", str(tmp_path / "full"), *common)
    assert set(_image_sizes(tmp_path / "full")) == {(160, 160)}
