"""Camera trajectories of the Realistic Synthetic 360 (nerf_synthetic) protocol, as plain maths.

The original data-generation script places the camera at (0, 4, 0.5) as the child of an Empty
at the origin, points it at the Empty with a Track-To constraint (-Z forward, +Y up) and moves
it by rotating the Empty (Euler XYZ: X tilt, Y = 0, Z azimuth).  This module reproduces that rig
in closed form so that poses can be tested without Blender and written identically by any
Blender version.

Deliberately standard library only (no numpy, no bpy, no I/O): Debian's `blender` binary ships
without numpy, and the generator must run there too.  Matrices are 4x4 row-major tuples (the
layout of `transform_matrix` in transforms_*.json); randomness comes from `random.Random`, whose
string seeding is stable across Python versions, so a seed gives the same poses everywhere.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Sequence, Tuple

Vector3 = Tuple[float, float, float]
Matrix4 = Tuple[Tuple[float, float, float, float], ...]

#: Camera position in the Empty's frame, as in the protocol's rig.
RIG_CAMERA_OFFSET: Vector3 = (0.0, 4.0, 0.5)
#: Distance of every camera from the origin: |(0, 4, 0.5)| = sqrt(16.25).
RIG_RADIUS: float = math.sqrt(16.25)
#: Elevation of the camera when the Empty is not tilted: the 0.5 height offset seen from 4 units.
RIG_BASE_ELEVATION: float = math.atan2(0.5, 4.0)
#: The protocol's test spiral tilts the Empty between 0 and this many radians.
TEST_SPIRAL_MAX_TILT: float = 0.7
#: Track-To's "up" target: the camera's +Y is kept as close as possible to world +Z.
WORLD_UP: Vector3 = (0.0, 0.0, 1.0)
#: The image's up where the view is along WORLD_UP (Track-To's choice in that degenerate case).
POLE_IMAGE_UP: Vector3 = (0.0, 1.0, 0.0)


@dataclass(frozen=True)
class RigPose:
    """One camera of the rig: the Empty's Euler angles and the resulting camera-to-world."""

    tilt_x: float  # Empty rotation about X (radians)
    azimuth_z: float  # Empty rotation about Z (radians)
    matrix: Matrix4  # camera-to-world, Blender/OpenGL camera (looks down -Z, +Y up)


def _sub(a: Sequence[float], b: Sequence[float]) -> Vector3:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _dot(a: Sequence[float], b: Sequence[float]) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Sequence[float], b: Sequence[float]) -> Vector3:
    return (
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    )


def _normalized(v: Sequence[float]) -> Vector3:
    length = math.sqrt(_dot(v, v))
    if length == 0.0:
        raise ValueError("cannot normalise a zero-length vector")
    return (v[0] / length, v[1] / length, v[2] / length)


def look_at(
    position: Sequence[float],
    target: Sequence[float] = (0.0, 0.0, 0.0),
    up: Sequence[float] = WORLD_UP,
) -> Matrix4:
    """Camera-to-world matrix of a camera at `position` looking at `target`.

    Blender/OpenGL camera convention (what Track-To with -Z forward and +Y up produces): the
    camera looks down its -Z axis, +X is image right, +Y is image up and leans towards `up`.
    Looking along `up` (a camera at the pole), roll is undefined: as Track-To does, the
    image's up is then world +Y, which for a camera straight above the target is the limit
    of the views approaching the pole at azimuth 0.
    """
    forward = _normalized(_sub(target, position))
    back = (-forward[0], -forward[1], -forward[2])
    right = _cross(forward, up)
    if _dot(right, right) < 1e-24:
        right = _cross(POLE_IMAGE_UP, back)
    right = _normalized(right)
    cam_up = _cross(back, right)
    return (
        (right[0], cam_up[0], back[0], float(position[0])),
        (right[1], cam_up[1], back[1], float(position[1])),
        (right[2], cam_up[2], back[2], float(position[2])),
        (0.0, 0.0, 0.0, 1.0),
    )


def rig_camera_position(tilt_x: float, azimuth_z: float) -> Vector3:
    """World position of the rig's camera when the Empty is rotated by Euler XYZ (tilt_x, 0, azimuth_z).

    Euler XYZ applies X first, then Z: position = Rz(azimuth_z) @ Rx(tilt_x) @ (0, 4, 0.5).
    """
    ox, oy, oz = RIG_CAMERA_OFFSET
    cos_x, sin_x = math.cos(tilt_x), math.sin(tilt_x)
    tilted = (ox, oy * cos_x - oz * sin_x, oy * sin_x + oz * cos_x)
    cos_z, sin_z = math.cos(azimuth_z), math.sin(azimuth_z)
    return (
        tilted[0] * cos_z - tilted[1] * sin_z,
        tilted[0] * sin_z + tilted[1] * cos_z,
        tilted[2],
    )


def rig_pose(tilt_x: float, azimuth_z: float) -> RigPose:
    """The camera pose the protocol's rig produces for one Empty rotation."""
    position = rig_camera_position(tilt_x, azimuth_z)
    return RigPose(tilt_x=tilt_x, azimuth_z=azimuth_z, matrix=look_at(position))


def split_rng(seed: int, split: str) -> random.Random:
    """An independent, reproducible random stream for one split (train and val never share draws)."""
    return random.Random(f"datasets_gen/{int(seed)}/{split}")


def hemisphere_poses(n: int, rng: random.Random, full_sphere: bool = False) -> list[RigPose]:
    """Random train/val views, uniform in direction as in the protocol.

    The Empty tilt X = arccos(1 - 2u) - pi/2 gives directions uniform on the sphere; the protocol
    folds it to the upper hemisphere with abs(), so elevations fall between atan(0.5/4) = 7.1 deg
    and 90 deg.  `full_sphere` keeps the sign (as the ficus scene does).  Azimuth Z = 2 pi v.
    """
    if n < 0:
        raise ValueError(f"number of views must be >= 0, got {n}")
    poses = []
    for _ in range(n):
        u, v = rng.random(), rng.random()
        tilt = math.acos(1.0 - 2.0 * u) - math.pi / 2.0
        if not full_sphere:
            tilt = abs(tilt)
        poses.append(rig_pose(tilt, 2.0 * math.pi * v))
    return poses


def test_spiral_poses(n: int = 200) -> list[RigPose]:
    """The protocol's fixed test path: two full turns, tilt oscillating once between 0.7 rad and 0.

    For n = 200 this is the published path: azimuth i * 3.6 deg from +Y, tilt
    (cos(1.8 deg * i) + 1) / 2 * 0.7 rad, i.e. elevation 47.2 deg -> 7.1 deg (frame 100) -> back.
    Other n keep two turns: azimuth step 720 deg / n, cosine step 360 deg / n.
    """
    if n < 0:
        raise ValueError(f"number of views must be >= 0, got {n}")
    poses = []
    for i in range(n):
        azimuth = i * test_spiral_azimuth_step(n)
        tilt = (math.cos(i * 2.0 * math.pi / n) + 1.0) / 2.0 * TEST_SPIRAL_MAX_TILT
        poses.append(rig_pose(tilt, azimuth))
    return poses


# Not a pytest test despite the name; tells pytest not to collect it when imported in tests.
test_spiral_poses.__test__ = False  # type: ignore[attr-defined]


def test_spiral_azimuth_step(n: int) -> float:
    """Azimuth step (radians) between consecutive test views: two full turns over n views."""
    return 4.0 * math.pi / n if n else 0.0


test_spiral_azimuth_step.__test__ = False  # type: ignore[attr-defined]


def rotation_step(n: int) -> float:
    """The per-frame "rotation" the protocol's script records: its step angle radians(360 / n).

    Loaders ignore it; it is kept for layout fidelity (the published test files hold 2 pi / 200).
    """
    return 2.0 * math.pi / n if n else 0.0
