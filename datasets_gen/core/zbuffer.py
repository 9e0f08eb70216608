"""Which surface points a pinhole camera sees: a depth buffer of the scene's triangles, and the
test of a point against it.

The COLMAP export (colmap_model) gives each surface point a track: the views that see it.  A
view sees a point when the point is inside its image and, along the ray through the centre of
the pixel the point falls in, the nearest surface is the point's own (its tangent plane's depth
there equals the depth buffer's, to a relative ``DEPTH_TOLERANCE``).  Points seen at grazing
angles (beyond ``GRAZING_COS``) are left out: their pixels are silhouettes, half background.

Cameras follow COLMAP: x right, y down, z forward; a pixel (i, j) covers [i, i+1) x [j, j+1) and
its centre is (i + 0.5, j + 0.5), as in a Cycles render (PROTOCOL.md).  Triangles that cross the
near plane are clipped to it; none is culled by its facing (Blender renders both sides).

numpy only, no bpy, no I/O.

Example: a unit square at depth 2, seen by a 4x4 camera, hides a point behind it:
    >>> camera = PinholeCamera(4, 4, 4.0, 4.0, 2.0, 2.0)
    >>> square = np.array([[-1, -1, 2], [1, -1, 2], [1, 1, 2], [-1, 1, 2]], float)
    >>> depth = depth_buffer(square, np.array([[0, 1, 2], [0, 2, 3]]), np.eye(3), np.zeros(3), camera)
    >>> float(depth.min()), float(depth.max())
    (2.0, 2.0)
    >>> points = np.array([[0.1, 0.1, 2.0], [0.1, 0.1, 3.0]])
    >>> normals = np.array([[0, 0, -1.0], [0, 0, -1.0]])
    >>> seen, _ = points_seen(points, normals, np.eye(3), np.zeros(3), camera, depth)
    >>> seen.tolist()
    [True, False]
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

NEAR = 1e-4
#: How far (relative) a point's depth may be from the nearest surface's and still be that surface.
DEPTH_TOLERANCE = 3e-3
#: Points whose surface meets the view ray at more than about 84 degrees from its normal are unseen.
GRAZING_COS = 0.1
#: Candidate pixels handled at once by the rasteriser (memory, not results).
CHUNK = 1 << 21


class PinholeCamera(NamedTuple):
    """COLMAP's PINHOLE model: image size and focal lengths and principal point in pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


def _clip_to_near(triangles: np.ndarray, near: float) -> np.ndarray:
    """The parts in front of the near plane of triangles [T, 3, 3] (camera frame) that cross it."""
    pieces = []
    for triangle in triangles:
        front = [corner for corner in triangle if corner[2] > near]
        polygon = []
        for k in range(3):
            a, b = triangle[k], triangle[(k + 1) % 3]
            if a[2] > near:
                polygon.append(a)
            if (a[2] > near) != (b[2] > near):
                s = (near - a[2]) / (b[2] - a[2])
                polygon.append(a + s * (b - a))
        if front:
            pieces.extend(np.array([polygon[0], polygon[k], polygon[k + 1]]) for k in range(1, len(polygon) - 1))
    return np.array(pieces).reshape(-1, 3, 3)


def depth_buffer(vertices: np.ndarray, faces: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                 camera: PinholeCamera) -> np.ndarray:
    """[height, width] depth (camera z) of the nearest triangle at each pixel centre; inf where none.

    ``rotation`` and ``translation`` take world points into the camera: p_cam = R p + t.
    """
    corners = (np.asarray(vertices, float) @ rotation.T + translation)[np.asarray(faces)]
    ahead = corners[..., 2] > NEAR
    triangles = np.concatenate([corners[ahead.all(axis=1)],
                                _clip_to_near(corners[ahead.any(axis=1) & ~ahead.all(axis=1)], NEAR)])
    depth = np.full(camera.height * camera.width, np.inf)
    if len(triangles) == 0:
        return depth.reshape(camera.height, camera.width)
    z = triangles[..., 2]
    u = camera.fx * triangles[..., 0] / z + camera.cx
    v = camera.fy * triangles[..., 1] / z + camera.cy
    # Pixel centres (i + 0.5) inside each triangle's bounding box, clamped to the image.
    x0 = np.clip(np.ceil(u.min(axis=1) - 0.5), 0, camera.width).astype(np.int64)
    x1 = np.clip(np.floor(u.max(axis=1) - 0.5), -1, camera.width - 1).astype(np.int64)
    y0 = np.clip(np.ceil(v.min(axis=1) - 0.5), 0, camera.height).astype(np.int64)
    y1 = np.clip(np.floor(v.max(axis=1) - 0.5), -1, camera.height - 1).astype(np.int64)
    area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
    span = np.maximum(x1 - x0, y1 - y0) + 1
    drawn = (x1 >= x0) & (y1 >= y0) & (np.abs(area) > 1e-12)
    size = 1
    while drawn.any():
        # Triangles whose box fits size x size pixels, a size class at a time, so each is
        # tested against at most 4 times its box's pixels.
        batch = np.flatnonzero(drawn & (span <= size))
        drawn[batch] = False
        offsets = np.stack(np.meshgrid(np.arange(size), np.arange(size)), axis=-1).reshape(-1, 2)
        for start in range(0, len(batch), max(1, CHUNK // (size * size))):
            _draw(depth, camera.width, batch[start:start + max(1, CHUNK // (size * size))], offsets,
                  u, v, z, area, x0, x1, y0, y1)
        size *= 2
    return depth.reshape(camera.height, camera.width)


def _draw(depth: np.ndarray, width: int, batch: np.ndarray, offsets: np.ndarray, u: np.ndarray, v: np.ndarray,
          z: np.ndarray, area: np.ndarray, x0: np.ndarray, x1: np.ndarray, y0: np.ndarray, y1: np.ndarray) -> None:
    px = x0[batch, None] + offsets[None, :, 0]
    py = y0[batch, None] + offsets[None, :, 1]
    keep = (px <= x1[batch, None]) & (py <= y1[batch, None])
    cx, cy = px + 0.5, py + 0.5
    ub, vb = u[batch][:, :, None], v[batch][:, :, None]
    # Barycentric weight of each corner: the signed area of the opposite edge and the point.
    weights = []
    for k in range(3):
        a, b = (k + 1) % 3, (k + 2) % 3
        edge = (ub[:, b] - ub[:, a]) * (cy - vb[:, a]) - (vb[:, b] - vb[:, a]) * (cx - ub[:, a])
        weights.append(edge / area[batch, None])
    inside = keep & (weights[0] >= -1e-9) & (weights[1] >= -1e-9) & (weights[2] >= -1e-9)
    # Perspective-correct: 1/z is linear across the image.
    inverse = sum(weight / z[batch, k, None] for k, weight in enumerate(weights))
    np.minimum.at(depth, (py * width + px)[inside], 1.0 / inverse[inside])


def project(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
            camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """(pixel coordinates [N, 2], camera depth [N]) of world points, in COLMAP's image convention."""
    in_camera = np.asarray(points, float) @ rotation.T + translation
    z = in_camera[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = np.stack([camera.fx * in_camera[:, 0] / z + camera.cx, camera.fy * in_camera[:, 1] / z + camera.cy],
                          axis=1)
    return pixels, z


def points_seen(points: np.ndarray, normals: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                camera: PinholeCamera, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(seen [N] bool, pixel coordinates [N, 2]) of surface points with unit normals, against the
    view's ``depth_buffer``."""
    pixels, z = project(points, rotation, translation, camera)
    inside = (z > NEAR) & (pixels[:, 0] >= 0) & (pixels[:, 0] < camera.width) \
        & (pixels[:, 1] >= 0) & (pixels[:, 1] < camera.height)
    seen = np.zeros(len(points), dtype=bool)
    index = np.flatnonzero(inside)
    if len(index) == 0:
        return seen, pixels
    i = np.floor(pixels[index, 0]).astype(np.int64)
    j = np.floor(pixels[index, 1]).astype(np.int64)
    in_camera = np.asarray(points, float)[index] @ rotation.T + translation
    normal = np.asarray(normals, float)[index] @ rotation.T
    facing = np.abs(np.einsum("ij,ij->i", normal, in_camera)) / np.linalg.norm(in_camera, axis=1)
    # The depth at which the ray through the pixel's centre meets the point's tangent plane.
    ray = np.stack([(i + 0.5 - camera.cx) / camera.fx, (j + 0.5 - camera.cy) / camera.fy, np.ones(len(i))], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        plane_depth = np.einsum("ij,ij->i", normal, in_camera) / np.einsum("ij,ij->i", normal, ray)
    nearest = depth[j, i]
    seen[index] = (facing >= GRAZING_COS) & (np.abs(nearest - plane_depth) <= DEPTH_TOLERANCE * plane_depth)
    return seen, pixels
