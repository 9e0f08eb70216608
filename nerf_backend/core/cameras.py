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


def rays_from_matrices(view: Tensor, projection: Tensor, width: int, height: int,
                       pixels: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Origins (on the near clip plane) and unit directions ``[H·W, 3]`` in world space of the
    pixels of a view as a graphics API gives it: ``view`` maps world to camera, ``projection``
    camera to OpenGL's clip space (Blender's ``RegionView3D.view_matrix`` and ``window_matrix``,
    a camera's ``calc_matrix_camera``). Pixels row-major from the top row, as ``camera_rays``'s;
    with ``pixels`` (their indices in that order), those pixels' rays only. Each pixel's centre
    is unprojected at the near and the far clip plane, so perspective and orthographic views
    alike (an orthographic view's rays are parallel).

    Example:
        >>> near, far = 0.1, 10.0  # a 90° perspective: the centre pixel looks down -Z
        >>> p = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, -(far + near) / (far - near),
        ...                   -2 * far * near / (far - near)], [0, 0, -1, 0]])
        >>> o, d = rays_from_matrices(torch.eye(4), p, 3, 3)
        >>> [round(v, 4) for v in o[4].tolist()], [round(v, 4) for v in d[4].tolist()]
        ([0.0, 0.0, -0.1], [0.0, 0.0, -1.0])
        >>> [round(v, 4) for v in d[0].tolist()]  # the top-left pixel: up and to the left
        [-0.4851, 0.4851, -0.7276]
        >>> torch.equal(rays_from_matrices(torch.eye(4), p, 3, 3, torch.tensor([0]))[1], d[:1])
        True
    """
    inverse = torch.linalg.inv(projection.double() @ view.double())
    if pixels is None:
        x = (torch.arange(width, dtype=torch.float64) + 0.5) * (2.0 / width) - 1.0
        y = 1.0 - (torch.arange(height, dtype=torch.float64) + 0.5) * (2.0 / height)
        # inverse @ (x, y, z, 1) as a sum of the inverse's columns: the clip points are never built.
        on_plane = (y[:, None, None] * inverse[:, 1] + x[None, :, None] * inverse[:, 0]).reshape(-1, 4)
    else:
        x = ((pixels % width).double() + 0.5) * (2.0 / width) - 1.0
        y = 1.0 - (torch.div(pixels, width, rounding_mode="floor").double() + 0.5) * (2.0 / height)
        on_plane = y[:, None] * inverse[:, 1] + x[:, None] * inverse[:, 0]
    ends = []
    for ndc_z in (-1.0, 1.0):
        world = on_plane + (ndc_z * inverse[:, 2] + inverse[:, 3])
        ends.append(world[:, :3] / world[:, 3:])
    directions = torch.nn.functional.normalize(ends[1] - ends[0], dim=-1)
    return ends[0].float().contiguous(), directions.float().contiguous()


def pixels_seeing_boxes(corners: Tensor, view: Tensor, projection: Tensor, width: int, height: int) -> Tensor | None:
    """The pixels (indices row-major from the top row, as ``rays_from_matrices`` takes them)
    whose centre's ray can meet one of the boxes of ``corners [N, 8, 3]`` (each box's eight
    corners, in ``view``'s world): those whose centre is inside a box's projected corners'
    rectangle, and a pixel round it. A ray through a box passes within the convex hull of its
    corners' projections, so a pixel left out sees none of the boxes. None where some corner
    is not in front of the camera (its projection would wrap round): every pixel may then see
    them.

    Example:
        >>> near, far = 0.1, 10.0  # a 90° perspective down -Z, 8×8 pixels
        >>> p = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, -(far + near) / (far - near),
        ...                   -2 * far * near / (far - near)], [0, 0, -1, 0]])
        >>> cube = torch.tensor([[x, y, z] for x in (0.5, 1.0) for y in (0.5, 1.0) for z in (-3.0, -2.0)])
        >>> seen = pixels_seeing_boxes(cube[None], torch.eye(4), p, 8, 8)  # its centre: column 5, row 2
        >>> sorted({int(i) % 8 for i in seen}), sorted({int(i) // 8 for i in seen})  # right of centre, above
        ([4, 5, 6], [1, 2, 3])
    """
    if corners.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64)
    to_clip = projection.double() @ view.double()
    clip = corners.double().reshape(-1, 3) @ to_clip[:, :3].T + to_clip[:, 3]
    if not bool((clip[:, 3] > 0).all()):
        return None
    ndc = (clip[:, :2] / clip[:, 3:]).reshape(-1, 8, 2)
    low, high = ndc.amin(dim=1), ndc.amax(dim=1)
    # Pixel i's centre is at x = (i + 0.5)·2/W - 1; row j's (from the top) at y = 1 - (j + 0.5)·2/H.
    # The columns and rows whose centres lie in the rectangle, and a pixel more for rounding.
    first_column = torch.ceil((low[:, 0] + 1) * (width / 2) - 0.5) - 1
    last_column = torch.floor((high[:, 0] + 1) * (width / 2) - 0.5) + 1
    first_row = torch.ceil((1 - high[:, 1]) * (height / 2) - 0.5) - 1
    last_row = torch.floor((1 - low[:, 1]) * (height / 2) - 0.5) + 1
    seen = (first_column < width) & (last_column >= 0) & (first_row < height) & (last_row >= 0)
    column_span = [first_column[seen].clamp(0, width - 1).long(), last_column[seen].clamp(0, width - 1).long() + 1]
    row_span = [first_row[seen].clamp(0, height - 1).long(), last_row[seen].clamp(0, height - 1).long() + 1]
    # The rectangles' union: +1 and -1 at their corners, summed along both axes.
    marks = torch.zeros((height + 1, width + 1), dtype=torch.int32)
    for rows, columns, sign in ((row_span[0], column_span[0], 1), (row_span[0], column_span[1], -1),
                                (row_span[1], column_span[0], -1), (row_span[1], column_span[1], 1)):
        marks.index_put_((rows, columns), torch.full_like(rows, sign, dtype=torch.int32), accumulate=True)
    covered = marks.cumsum(0).cumsum(1)[:height, :width] > 0
    return covered.reshape(-1).nonzero().squeeze(1)


def camera_z_along_rays(view: Tensor, origins: Tensor, directions: Tensor, distance: Tensor) -> Tensor:
    """The distance in front of the camera, along its view axis (``-z`` in camera space: what a
    depth buffer linearises to), of the points ``origins + distance · directions`` (``[N, 3]``
    and ``[N]``, in the frame ``view`` maps to camera space).

    Example:
        >>> camera_z_along_rays(torch.eye(4), torch.tensor([[1.0, 2.0, 0.0]]), torch.tensor([[0.0, 0.0, -1.0]]),
        ...                     torch.tensor([3.0])).tolist()
        [3.0]
    """
    axis, offset = -view[2, :3].to(origins.dtype), -float(view[2, 3])
    return origins @ axis + offset + distance * (directions @ axis)
