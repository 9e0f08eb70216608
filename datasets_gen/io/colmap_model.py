"""A COLMAP sparse model of a rendered dataset: exact cameras and poses, and 3D points sampled on
the scene's true surface with the tracks of the views that see them.

COLMAP's conventions (https://colmap.github.io/format.html): a camera looks down +z with x right
and y down; an image's pose is world-to-camera, a unit quaternion (QW, QX, QY, QZ) and a
translation (p_cam = R p_world + t); the camera model here is PINHOLE (fx, fy, cx, cy), the
centre of the top-left pixel at (0.5, 0.5).  nerf_synthetic's camera-to-world matrices are
OpenGL's (y up, z backward): the two differ by a flip of the camera's y and z axes.

Each point's colour is the mean over the views that see it of the render at its 2D point,
interpolated as COLMAP's own colour extraction does (bilinear, pixel centres at + 0.5), and its
error (COLMAP's mean reprojection error) is 0: its 2D points are its exact projections.

numpy only, no bpy, no I/O (colmap_export reads the dataset and writes the files).

Example: a nerf_synthetic camera on the +z axis 4 units out, looking back at the origin, is in
COLMAP's convention a half-turn about x with the origin 4 units ahead:
    >>> camera_to_world = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]
    >>> rotation, translation = world_to_camera(camera_to_world)
    >>> quaternion(rotation).round(6).tolist(), translation.tolist()
    ([0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 4.0])
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..core.zbuffer import PinholeCamera, points_seen

#: COLMAP's model id of PINHOLE (cameras.bin) and its parameters' order.
PINHOLE_ID = 1
#: OpenGL camera axes (y up, z backward) to COLMAP's (y down, z forward).
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def world_to_camera(camera_to_world: Sequence[Sequence[float]]) -> tuple[np.ndarray, np.ndarray]:
    """(rotation [3, 3], translation [3]) in COLMAP's convention of a nerf_synthetic
    ``transform_matrix`` (OpenGL camera-to-world)."""
    matrix = np.asarray(camera_to_world, dtype=float)
    rotation = (matrix[:3, :3] @ FLIP_YZ).T
    return rotation, -rotation @ matrix[:3, 3]


def quaternion(rotation: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method: from
    the largest of the four squared components, so no division by a small number)."""
    m = np.asarray(rotation, dtype=float)
    squares = np.array([1 + m[0, 0] + m[1, 1] + m[2, 2], 1 + m[0, 0] - m[1, 1] - m[2, 2],
                        1 - m[0, 0] + m[1, 1] - m[2, 2], 1 - m[0, 0] - m[1, 1] + m[2, 2]])
    k = int(np.argmax(squares))
    s = 2.0 * np.sqrt(squares[k])
    if k == 0:
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        q = [(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s]
    else:
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4]
    q = np.array(q)
    return (q if q[0] >= 0 else -q) / np.linalg.norm(q)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int,
                   seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(points [count, 3], unit normals [count, 3]) uniform by area on a triangle mesh; the same
    mesh and seed give the same points.

    >>> square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    >>> points, normals = sample_surface(square, np.array([[0, 1, 2], [0, 2, 3]]), 1000, seed=0)
    >>> bool((points[:, 2] == 0).all()), normals[0].tolist(), round(float(points[:, :2].mean()), 1)
    (True, [0.0, 0.0, 1.0], 0.5)
    """
    corners = np.asarray(vertices, dtype=float)[np.asarray(faces)]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(cross, axis=1)
    if not area.sum() > 0:
        raise ValueError("the surface has no area to sample")
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(faces), size=count, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    a, b, c = corners[chosen, 0], corners[chosen, 1], corners[chosen, 2]
    points = (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b + (r1 * r2)[:, None] * c
    return points, cross[chosen] / area[chosen, None]


@dataclass
class ColmapImage:
    """One registered image: its pose, camera and observations (2D points and their 3D ids)."""

    image_id: int
    camera_id: int
    name: str
    rotation: np.ndarray  # [3, 3] world to camera
    translation: np.ndarray  # [3]
    points2d: np.ndarray  # [K, 2] pixel coordinates
    point3d_ids: np.ndarray  # [K] int64


@dataclass
class ColmapModel:
    """Cameras, images and the 3D points with their tracks (rows of ``track`` are (point row,
    image id, index of the 2D point in that image), sorted by point row then image id)."""

    cameras: dict[int, PinholeCamera]
    images: list[ColmapImage]
    point_ids: np.ndarray  # [M] int64, from 1
    xyz: np.ndarray  # [M, 3]
    normals: np.ndarray  # [M, 3]
    rgb: np.ndarray  # [M, 3] uint8
    track: np.ndarray  # [O, 3] int64

    def mean_track_length(self) -> float:
        return len(self.track) / max(1, len(self.point_ids))


def bilinear(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """[N, C] colours of an [H, W, C] image at COLMAP pixel coordinates (centres at i + 0.5),
    interpolated between the four nearest centres (clamped at the border).

    >>> image = np.array([[[0.0], [10.0]], [[20.0], [30.0]]])
    >>> bilinear(image, np.array([[1.0, 1.0], [0.5, 0.5], [9.0, 0.0]])).ravel().tolist()
    [15.0, 0.0, 10.0]
    """
    height, width = image.shape[:2]
    x = np.clip(pixels[:, 0] - 0.5, 0, width - 1)
    y = np.clip(pixels[:, 1] - 0.5, 0, height - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), width - 2) if width > 1 else np.zeros(len(x), np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), height - 2) if height > 1 else np.zeros(len(y), np.int64)
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    image = np.asarray(image, dtype=float)
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x1])
            + fy * ((1 - fx) * image[y1, x0] + fx * image[y1, x1]))


class TrackBuilder:
    """Collects, view by view, which surface points each view sees and the colours it renders them."""

    def __init__(self, points: np.ndarray, normals: np.ndarray) -> None:
        self.points, self.normals = points, normals
        self.colour_sum = np.zeros((len(points), 3))
        self.seen_by = np.zeros(len(points), dtype=np.int64)
        self.views: list[tuple[int, int, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def add_view(self, image_id: int, camera_id: int, name: str, rotation: np.ndarray, translation: np.ndarray,
                 camera: PinholeCamera, depth: np.ndarray, rgb: np.ndarray) -> None:
        """Observe the points this view sees (``depth``: its depth buffer; ``rgb``: its render,
        [H, W, 3] uint8)."""
        seen, pixels = points_seen(self.points, self.normals, rotation, translation, camera, depth)
        rows = np.flatnonzero(seen)
        self.colour_sum[rows] += bilinear(rgb, pixels[rows])
        self.seen_by[rows] += 1
        self.views.append((image_id, camera_id, name, rotation, translation, rows, pixels[rows]))

    def model(self, cameras: dict[int, PinholeCamera]) -> ColmapModel:
        """The model of the points seen by at least one view (numbered from 1 in sampling order)."""
        kept = self.seen_by > 0
        point_id = np.zeros(len(self.points), dtype=np.int64)
        point_id[kept] = np.arange(1, int(kept.sum()) + 1)
        images, track = [], []
        for image_id, camera_id, name, rotation, translation, rows, pixels in self.views:
            images.append(ColmapImage(image_id, camera_id, name, rotation, translation, pixels, point_id[rows]))
            track.append(np.stack([point_id[rows] - 1, np.full(len(rows), image_id), np.arange(len(rows))], axis=1))
        track_rows = np.concatenate(track) if track else np.zeros((0, 3), dtype=np.int64)
        track_rows = track_rows[np.lexsort((track_rows[:, 1], track_rows[:, 0]))]
        colours = self.colour_sum[kept] / self.seen_by[kept, None]
        return ColmapModel(cameras, images, point_id[kept], self.points[kept], self.normals[kept],
                           np.clip(np.round(colours), 0, 255).astype(np.uint8), track_rows.astype(np.int64))


# --- COLMAP's text files -------------------------------------------------------------------------

def _numbers(values: np.ndarray) -> list[str]:
    return [repr(float(value)) for value in np.asarray(values, dtype=float).ravel()]


def cameras_text(model: ColmapModel) -> str:
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {len(model.cameras)}"]
    for camera_id, camera in sorted(model.cameras.items()):
        lines.append(" ".join([str(camera_id), "PINHOLE", str(camera.width), str(camera.height),
                               *_numbers(np.array([camera.fx, camera.fy, camera.cx, camera.cy]))]))
    return "\n".join(lines) + "\n"


def images_text(model: ColmapModel) -> str:
    observations = sum(len(image.point3d_ids) for image in model.images)
    lines = ["# Image list with two lines of data per image:",
             "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)",
             f"# Number of images: {len(model.images)}, mean observations per image: "
             f"{observations / max(1, len(model.images))}"]
    for image in model.images:
        lines.append(" ".join([str(image.image_id), *_numbers(quaternion(image.rotation)),
                               *_numbers(image.translation), str(image.camera_id), image.name]))
        # 2D points to 1e-6 px (the .bin files hold them exactly): a third of the file's size.
        lines.append(" ".join(f"{x:.6f} {y:.6f} {point_id}"
                              for (x, y), point_id in zip(image.points2d.tolist(), image.point3d_ids.tolist())))
    return "\n".join(lines) + "\n"


def points3d_text(model: ColmapModel) -> str:
    lines = ["# 3D point list with one line of data per point:",
             "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
             f"# Number of points: {len(model.point_ids)}, mean track length: {model.mean_track_length()}"]
    starts = np.searchsorted(model.track[:, 0], np.arange(len(model.point_ids) + 1))
    xyz = _numbers(model.xyz)
    for row, point_id in enumerate(model.point_ids.tolist()):
        track = model.track[starts[row]:starts[row + 1], 1:].ravel().tolist()
        lines.append(" ".join([str(point_id), *xyz[3 * row:3 * row + 3], *map(str, model.rgb[row].tolist()), "0.0",
                               *map(str, track)]))
    return "\n".join(lines) + "\n"


# --- COLMAP's binary files (little-endian, as its read_write_model.py reads them) ------------------

def cameras_binary(model: ColmapModel) -> bytes:
    parts = [struct.pack("<Q", len(model.cameras))]
    for camera_id, camera in sorted(model.cameras.items()):
        parts.append(struct.pack("<iiQQ4d", camera_id, PINHOLE_ID, camera.width, camera.height,
                                 camera.fx, camera.fy, camera.cx, camera.cy))
    return b"".join(parts)


def images_binary(model: ColmapModel) -> bytes:
    parts = [struct.pack("<Q", len(model.images))]
    observation = np.dtype([("x", "<f8"), ("y", "<f8"), ("point3d_id", "<i8")])
    for image in model.images:
        parts.append(struct.pack("<i4d3di", image.image_id, *quaternion(image.rotation), *image.translation,
                                 image.camera_id))
        parts.append(image.name.encode("utf-8") + b"\0")
        rows = np.empty(len(image.point3d_ids), dtype=observation)
        rows["x"], rows["y"], rows["point3d_id"] = image.points2d[:, 0], image.points2d[:, 1], image.point3d_ids
        parts.append(struct.pack("<Q", len(rows)) + rows.tobytes())
    return b"".join(parts)


def points3d_binary(model: ColmapModel) -> bytes:
    parts = [struct.pack("<Q", len(model.point_ids))]
    starts = np.searchsorted(model.track[:, 0], np.arange(len(model.point_ids) + 1))
    for row, point_id in enumerate(model.point_ids.tolist()):
        track = model.track[starts[row]:starts[row + 1], 1:].astype("<i4")
        parts.append(struct.pack("<Q3d3Bd", point_id, *model.xyz[row], *model.rgb[row], 0.0))
        parts.append(struct.pack("<Q", len(track)) + track.tobytes())
    return b"".join(parts)


def points_ply_bytes(xyz: np.ndarray, normals: np.ndarray, rgb: np.ndarray, comment: str) -> bytes:
    """A binary little-endian PLY of points: x y z nx ny nz (float) red green blue (uchar), the
    layout the original 3D Gaussian Splatting code reads as its initial point cloud."""
    rows = np.empty(len(xyz), dtype=[("xyz", "<f4", (3,)), ("normal", "<f4", (3,)), ("rgb", "u1", (3,))])
    rows["xyz"], rows["normal"], rows["rgb"] = xyz, normals, rgb
    header = (f"ply\nformat binary_little_endian 1.0\ncomment {comment}\nelement vertex {len(xyz)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    return header.encode("ascii") + rows.tobytes()
