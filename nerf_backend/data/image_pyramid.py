"""Training images at coarser sizes, for coarse-to-fine training: while a model still holds
only coarse detail, its rays come from images downsampled to that detail, so an 800×800
dataset starts like a 100×100 one (each ray's colour is the mean over the footprint the
coarse model can resolve, not one point of it).

A pixel of the image downsampled by ``factor`` is the mean of a ``factor × factor`` block of
full-size pixels, taken over premultiplied colour (colour·α), so that compositing it over any
background equals the mean of the block composited over that background. Its centre is the
block's centre, so its ray is the block's middle ray (``block_intrinsics``). Pure maths, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.cameras import Intrinsics

# The coarsest level keeps at least this many pixels along the image's shorter side: an
# 800×800 dataset starts at 100×100, a 100×100 one is never downsampled.
MIN_LEVEL_SIDE = 64


def block_intrinsics(intrinsics: Intrinsics, factor: int) -> Intrinsics:
    """The intrinsics of images downsampled by ``factor`` in whole blocks (a remainder of
    fewer than ``factor`` rows or columns at the bottom and right is left out): pixel ``i``
    of the coarse image is the block of full-size pixels ``[factor·i, factor·i + factor)``,
    whose centre ``factor·(i + 0.5)`` is the coarse pixel's centre ``i + 0.5``. (Unlike
    ``Intrinsics.scaled``, which keeps the whole field of view at a rounded size.)

    Example:
        >>> k = block_intrinsics(Intrinsics(801, 800, 1111.1, 1111.1, 400.5, 400.0), 4)
        >>> k.width, k.height, round(k.fl_x, 3), k.cx, k.cy
        (200, 200, 277.775, 100.125, 100.0)
    """
    return Intrinsics(intrinsics.width // factor, intrinsics.height // factor, intrinsics.fl_x / factor,
                      intrinsics.fl_y / factor, intrinsics.cx / factor, intrinsics.cy / factor)


def downsample_rgba(rgba: Tensor, factor: int) -> Tensor:
    """``uint8 [N, H, W, 4]`` → ``uint8 [N, H // factor, W // factor, 4]``: each pixel the
    mean of its block, colour averaged premultiplied by alpha (a block half transparent and
    half red is red at α = 0.5, not dark red). Converted an image at a time, so no float copy
    of the whole set is ever made.

    Example:
        >>> red, clear = [255, 0, 0, 255], [0, 0, 0, 0]
        >>> block = torch.tensor([[[red, clear], [red, clear]]], dtype=torch.uint8)  # [1, 2, 2, 4]
        >>> downsample_rgba(block, 2)[0, 0, 0].tolist()
        [255, 0, 0, 128]
    """
    if factor == 1:
        return rgba
    count, height, width, _ = rgba.shape
    rows, cols = height // factor, width // factor
    out = torch.empty((count, rows, cols, 4), dtype=torch.uint8, device=rgba.device)
    for index in range(count):
        image = rgba[index, :rows * factor, :cols * factor].float()
        alpha = image[..., 3:4]
        premultiplied = torch.cat([image[..., :3] * alpha / 255.0, alpha], dim=-1)
        mean = premultiplied.view(rows, factor, cols, factor, 4).mean(dim=(1, 3))
        mean_alpha = mean[..., 3:4]
        colour = torch.where(mean_alpha > 0, mean[..., :3] * 255.0 / mean_alpha.clamp_min(1e-6), 0.0)
        out[index] = torch.cat([colour, mean_alpha], dim=-1).round().clamp(0, 255).to(torch.uint8)
    return out


def level_factor(pixel_size: float, detail: float | None, width: int, height: int) -> int:
    """The downsampling factor for a model whose finest detail is ``detail`` (world units;
    None: it holds its final detail, so train on the full images), ``pixel_size`` the size of
    a full-size pixel on the scene: the largest power of two whose pixels are no larger than
    that detail, keeping at least ``MIN_LEVEL_SIDE`` pixels along the shorter side.

    Example:
        >>> level_factor(0.0036, 0.05, 800, 800), level_factor(0.0036, 0.016, 800, 800)
        (8, 4)
        >>> level_factor(0.0036, None, 800, 800), level_factor(0.029, 0.05, 100, 100)
        (1, 1)
    """
    factor = 1
    if detail is None:
        return factor
    while 2 * factor * pixel_size <= detail and min(width, height) // (2 * factor) >= MIN_LEVEL_SIDE:
        factor *= 2
    return factor


@dataclass(frozen=True)
class ImageLevel:
    """The training images at one size: ``rgba`` uint8 ``[N, h, w, 4]`` and their intrinsics."""

    factor: int
    rgba: Tensor
    intrinsics: Intrinsics


class ImagePyramid:
    """The training images and their downsampled levels, each made on first use; asking for
    the full size lets the coarser levels go (training never goes back to them)."""

    def __init__(self, rgba: Tensor, intrinsics: Intrinsics) -> None:
        self.full = ImageLevel(1, rgba, intrinsics)
        self._levels: dict[int, ImageLevel] = {}

    def level(self, factor: int) -> ImageLevel:
        if factor == 1:
            self._levels.clear()
            return self.full
        if factor not in self._levels:
            self._levels[factor] = ImageLevel(factor, downsample_rgba(self.full.rgba, factor),
                                              block_intrinsics(self.full.intrinsics, factor))
        return self._levels[factor]
