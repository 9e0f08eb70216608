"""Rays through pixel centres, from exact pinhole intrinsics and camera-to-world poses.

Conventions (the nerf_synthetic ones, which are Blender's): the camera looks down its -Z
axis with +Y up; pixel (i, j) of a W×H image has its centre at (i + 0.5, j + 0.5) measured
from the image's top-left corner with y pointing down, as in a Cycles render. ``cx, cy``
are in that same frame, so an unshifted camera has ``cx = W / 2, cy = H / 2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (y down, pixel centres at i + 0.5)."""

    width: int
    height: int
    fl_x: float
    fl_y: float
    cx: float
    cy: float

    @classmethod
    def from_camera_angle_x(cls, width: int, height: int, camera_angle_x: float) -> "Intrinsics":
        """The reference loaders' intrinsics: square pixels, principal point at the centre."""
        focal = 0.5 * width / math.tan(0.5 * camera_angle_x)
        return cls(width, height, focal, focal, width / 2.0, height / 2.0)

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the same camera at ``factor`` times the resolution."""
        width, height = round(self.width * factor), round(self.height * factor)
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fl_x * sx, self.fl_y * sy, self.cx * sx, self.cy * sy)


def pixel_centres(width: int, flat_index: Tensor) -> Tensor:
    """Centres ``[R, 2]`` (x, y) of the pixels with row-major indices ``flat_index [R]``
    in an image ``width`` pixels wide."""
    x = (flat_index % width).to(torch.float32) + 0.5
    y = torch.div(flat_index, width, rounding_mode="floor").to(torch.float32) + 0.5
    return torch.stack([x, y], dim=-1)


def camera_rays(
    intrinsics: Intrinsics, camera_to_world: Tensor, pixels_xy: Tensor
) -> tuple[Tensor, Tensor]:
    """Origins and unit directions of the rays through ``pixels_xy``.

    Args:
        intrinsics: the camera's pinhole intrinsics.
        camera_to_world: ``[4, 4]`` pose, or ``[R, 4, 4]`` one per ray.
        pixels_xy: ``[R, 2]`` image-plane coordinates (x right, y down), e.g. pixel centres.

    Returns:
        ``origins [R, 3]`` and ``directions [R, 3]`` (unit length) in world space.

    Example:
        >>> k = Intrinsics(2, 2, 1.0, 1.0, 1.0, 1.0)
        >>> o, d = camera_rays(k, torch.eye(4), torch.tensor([[1.0, 1.0]]))
        >>> d.tolist()  # the principal point looks straight down -Z
        [[0.0, 0.0, -1.0]]
    """
    x_cam = (pixels_xy[:, 0] - intrinsics.cx) / intrinsics.fl_x
    y_cam = -(pixels_xy[:, 1] - intrinsics.cy) / intrinsics.fl_y  # image y is down, camera y up
    dirs_cam = torch.stack([x_cam, y_cam, -torch.ones_like(x_cam)], dim=-1)
    rotation = camera_to_world[..., :3, :3]
    if rotation.dim() == 2:
        dirs_world = dirs_cam @ rotation.T
        origins = camera_to_world[:3, 3].expand_as(dirs_world)
    else:
        dirs_world = torch.einsum("rij,rj->ri", rotation, dirs_cam)
        origins = camera_to_world[:, :3, 3]
    directions = dirs_world / torch.linalg.norm(dirs_world, dim=-1, keepdim=True)
    return origins.contiguous(), directions


def project_points(intrinsics: Intrinsics, camera_to_world: Tensor, points: Tensor) -> Tensor:
    """Image-plane coordinates ``[N, 2]`` (x right, y down) of world ``points [N, 3]``."""
    world_to_camera = torch.linalg.inv(camera_to_world)
    p_cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    depth = -p_cam[:, 2]
    x = intrinsics.cx + intrinsics.fl_x * p_cam[:, 0] / depth
    y = intrinsics.cy - intrinsics.fl_y * p_cam[:, 1] / depth
    return torch.stack([x, y], dim=-1)


def ray_box_intersection(
    origins: Tensor, directions: Tensor, box_min: Tensor, box_max: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Slab test: the entry and exit distances of each ray through an axis-aligned box.

    Returns ``t_near [R]``, ``t_far [R]`` and ``hit [R]`` (bool). Entry is clamped at 0 so a
    camera inside the box starts at its own position. For rays that miss, ``t_near ==
    t_far`` so any samples between them carry zero length and render as background.
    """
    # Axis-parallel rays have a zero component: use a huge finite reciprocal, not inf, so
    # 0 * inf never makes a NaN.
    tiny = torch.copysign(torch.full_like(directions, 1e-12), directions)
    inv = 1.0 / torch.where(directions.abs() < 1e-12, tiny, directions)
    t0 = (box_min - origins) * inv
    t1 = (box_max - origins) * inv
    t_near = torch.minimum(t0, t1).amax(dim=-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(dim=-1)
    hit = t_far > t_near
    t_far = torch.where(hit, t_far, t_near)
    return t_near, t_far, hit
