"""Rendering whole images from a trained model, in chunks of rays so memory stays bounded
whatever the resolution."""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ..core.cameras import Intrinsics
from ..core.files import write_exr, write_png
from ..model_components.compiled_march import pixel_rays
from ..model_components.ray_bounds import RayBounds
from ..models.base import Model, final_output


@dataclass
class RenderedImage:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1], over white
    depth: np.ndarray  # [H, W] float32, expected distance along the ray (0 where empty)
    opacity: np.ndarray  # [H, W] float32 in [0, 1]


@torch.no_grad()
def render_image(
    model: Model, intrinsics: Intrinsics, camera_to_world: Tensor, ray_bounds: RayBounds,
    chunk: int | None = None,
) -> RenderedImage:
    """Render one view deterministically; peak memory scales with ``chunk``, not the image."""
    device = next(model.parameters()).device
    pose = camera_to_world.to(device)
    height, width = intrinsics.height, intrinsics.width

    def rays(start: int, stop: int) -> tuple[Tensor, Tensor]:
        # This chunk's pixels only: the full grid would be O(H·W) memory.
        return pixel_rays(intrinsics, pose, start, stop)

    rgb, depth, opacity = render_rays(model, rays, height * width, ray_bounds, chunk)
    return RenderedImage(rgb.reshape(height, width, 3), depth.reshape(height, width), opacity.reshape(height, width))


@torch.no_grad()
def render_rays(model: Model, rays: Callable[[int, int], tuple[Tensor, Tensor]], count: int, ray_bounds: RayBounds,
                chunk: int | None = None, background: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour ``[N, 3]`` (over ``background``), expected depth ``[N]`` and opacity ``[N]`` of
    ``count`` rays, ``rays(start, stop)`` giving the origins and unit directions of rays
    ``start`` to ``stop`` on the model's device, ``chunk`` rays a pass."""
    chunk = chunk if chunk is not None else model.render_chunk
    was_training = model.training
    model.eval()
    rgb = np.empty((count, 3), np.float32)
    depth = np.empty(count, np.float32)
    opacity = np.empty(count, np.float32)
    for start in range(0, count, chunk):
        stop = min(start + chunk, count)
        origins, directions = rays(start, stop)
        t_near, t_far = ray_bounds(origins, directions)
        out = final_output(model(origins, directions, t_near, t_far, background=background))
        rgb[start:stop] = out.rgb.clamp(0, 1).float().cpu().numpy()
        depth[start:stop] = out.depth.float().cpu().numpy()
        opacity[start:stop] = out.opacity.clamp(0, 1).float().cpu().numpy()
    model.train(was_training)
    return rgb, depth, opacity


def save_rendered(image: RenderedImage, out_dir: Path, stem: str) -> Path:
    """``stem.png`` (RGB over white) and ``stem_depth.exr`` (channels Z and A = opacity)."""
    png = out_dir / f"{stem}.png"
    write_png(png, image.rgb)
    write_exr(out_dir / f"{stem}_depth.exr", {"Z": image.depth, "A": image.opacity})
    return png


def render_poses(
    model: Model, intrinsics: Intrinsics, poses: Tensor, stems: list[str], ray_bounds: RayBounds,
    out_dir: Path, chunk: int | None = None, on_view: Callable[[int, RenderedImage], None] | None = None,
    writer: Executor | None = None,
) -> list[Path]:
    """Render and save every pose; ``on_view(i, image)`` is called once view ``i``'s files are
    written, with the image they hold.
    ``writer``: an executor that writes each view (then calls ``on_view``) while the next one
    renders; every view is written when this returns."""
    paths, writes = [], []
    for i, (pose, stem) in enumerate(zip(poses, stems)):
        image = render_image(model, intrinsics, pose, ray_bounds, chunk)
        if writer is None:
            paths.append(_save_and_tell(image, out_dir, stem, on_view, i))
        else:
            writes.append(writer.submit(_save_and_tell, image, out_dir, stem, on_view, i))
    return paths + [write.result() for write in writes]


def _save_and_tell(image: RenderedImage, out_dir: Path, stem: str,
                   on_view: Callable[[int, RenderedImage], None] | None, index: int) -> Path:
    path = save_rendered(image, out_dir, stem)
    if on_view is not None:
        on_view(index, image)
    return path
