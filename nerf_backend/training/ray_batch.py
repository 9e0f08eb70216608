"""A training step's batch of rays: random pixels of the training images (from their centres
during the precrop, where the error is with an error map), their targets composited over the
step's background.

Example:
    >>> import torch
    >>> images = torch.zeros((2, 4, 6, 4), dtype=torch.uint8)
    >>> image, pixel = sample_ray_batch(images, 5, torch.Generator().manual_seed(0), None)
    >>> image.shape, bool((pixel < 24).all())
    (torch.Size([5]), True)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..data.dataset import composite
from ..data.image_pyramid import ImageLevel
from .error_map import ErrorMap


@dataclass(frozen=True)
class RayBatch:
    image: torch.Tensor  # [B] the view of each ray
    pixel: torch.Tensor  # [B] its row-major pixel
    target: torch.Tensor  # [B, 3] the pixel composited over the background
    background: torch.Tensor  # [B, 3] random colours, or white ([])


def draw_batch(images: ImageLevel, rays: int, generator: torch.Generator, precrop_fraction: float | None,
               error_map: ErrorMap | None, random_background: bool, device: torch.device) -> RayBatch:
    """``rays`` random pixels of ``images`` (the error map's draw after the precrop, where
    there is one) and their targets over random colours or white."""
    width, height = images.intrinsics.width, images.intrinsics.height
    if error_map is not None and precrop_fraction is None:
        image, pixel = error_map.sample(rays, height, width, generator)
    else:
        image, pixel = sample_ray_batch(images.rgba, rays, generator, precrop_fraction)
    image, pixel = image.to(device), pixel.to(device)
    pixels_rgba = images.rgba[image, pixel // width, pixel % width]
    if random_background:
        background = torch.rand((len(pixel), 3), generator=generator).to(device)
    else:
        background = torch.ones((), device=device)
    return RayBatch(image, pixel, composite(pixels_rgba, background), background)


def sample_ray_batch(
    rgba: torch.Tensor, batch: int, generator: torch.Generator, precrop_fraction: float | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Random (image, pixel) indices into images ``rgba [N, H, W, 4]``: ``image [B]`` and
    row-major ``pixel [B]``, drawn from the central ``precrop_fraction`` of each image when given."""
    count, height, width = rgba.shape[:3]
    image = torch.randint(count, (batch,), generator=generator)
    if precrop_fraction is None:
        x = torch.randint(width, (batch,), generator=generator)
        y = torch.randint(height, (batch,), generator=generator)
    else:
        half_w = max(1, int(width * precrop_fraction / 2))
        half_h = max(1, int(height * precrop_fraction / 2))
        x = torch.randint(width // 2 - half_w, width // 2 + half_w, (batch,), generator=generator)
        y = torch.randint(height // 2 - half_h, height // 2 + half_h, (batch,), generator=generator)
    return image, y * width + x
