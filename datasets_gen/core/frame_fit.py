"""The similarity transform that maps a Blender scene into the protocol's (NeRF) frame.

Real scenes sit anywhere and at any scale, while every protocol camera is at radius 4.0311
looking at the origin.  Rather than moving the user's scene, the dataset camera is placed in
Blender's world at the inverse-mapped pose; the rendered image is the same (a pinhole image is
invariant under a similarity of scene and camera together), the user's scene is untouched,
and the dataset records the transform so that poses and points can be mapped both ways:

    p_nerf = scale * p_blender + translation        (uniform scale, no rotation)

Camera rotations are unchanged by it, so a camera-to-world matrix maps by mapping its position.

Standard library only (no bpy): decided and tested as plain maths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

from .intrinsics import Intrinsics
from .trajectories import RIG_RADIUS, Matrix4, Vector3

#: Room kept around the fitted object in the narrowest view: its sphere fills 90 % of the cone.
FIT_MARGIN = 0.1

#: The thinnest a side of the profile's bounds may be, as a share of the longest side.
MIN_THICKNESS = 0.04

FIT_RULE = (
    "fit: the renderable geometry's bounding sphere (centre = centre of its axis-aligned bounds, "
    "radius = distance from that centre to the farthest vertex) is moved to the origin and scaled "
    "to radius (1 - margin) * 4.0311 * sin(half_angle), half_angle being the narrowest angle "
    "between the optical axis and the image border (both axes, lens shift included), so that "
    "the whole object stays inside every protocol view"
)
BLENDER_RULE = "blender: identity; the scene is rendered where it is in Blender's world"
DEMO_RULE = "blender: identity; the built-in demo scene is modelled in the protocol frame"


@dataclass(frozen=True)
class Similarity:
    """p_nerf = scale * p_blender + translation (scale > 0)."""

    scale: float
    translation: Vector3

    def apply(self, point: Sequence[float]) -> Vector3:
        """A Blender world point in the NeRF frame."""
        s, t = self.scale, self.translation
        return (s * point[0] + t[0], s * point[1] + t[1], s * point[2] + t[2])

    def inverse_apply(self, point: Sequence[float]) -> Vector3:
        """A NeRF-frame point in Blender's world."""
        s, t = self.scale, self.translation
        return ((point[0] - t[0]) / s, (point[1] - t[1]) / s, (point[2] - t[2]) / s)

    def camera_to_nerf(self, matrix: Sequence[Sequence[float]]) -> Matrix4:
        """A Blender camera-to-world matrix (rotation, position) as a NeRF-frame one."""
        return _with_position(matrix, self.apply([matrix[0][3], matrix[1][3], matrix[2][3]]))

    def camera_to_blender(self, matrix: Sequence[Sequence[float]]) -> Matrix4:
        """A NeRF-frame camera-to-world matrix as the Blender camera that renders the same image."""
        return _with_position(matrix, self.inverse_apply([matrix[0][3], matrix[1][3], matrix[2][3]]))

    def bounds(self, low: Sequence[float], high: Sequence[float]) -> tuple[list[float], list[float]]:
        """Axis-aligned bounds in the NeRF frame (a positive uniform scale keeps min below max)."""
        return list(self.apply(low)), list(self.apply(high))

    def matrix(self) -> list[list[float]]:
        """The 4x4 row-major matrix of the transform (homogeneous points as columns)."""
        s, t = self.scale, self.translation
        return [
            [s, 0.0, 0.0, t[0]],
            [0.0, s, 0.0, t[1]],
            [0.0, 0.0, s, t[2]],
            [0.0, 0.0, 0.0, 1.0],
        ]

    def record(self, rule: str, **details: Any) -> dict[str, Any]:
        """The `world_to_nerf` JSON record: scale, translation, matrix, the rule and its inputs."""
        document: dict[str, Any] = {
            "scale": self.scale,
            "translation": [float(value) for value in self.translation],
            "matrix": self.matrix(),
            "convention": "p_nerf = scale * p_blender_world + translation; rotations unchanged",
            "rule": rule,
        }
        document.update(details)
        return document


IDENTITY = Similarity(1.0, (0.0, 0.0, 0.0))


def thickened(low: Sequence[float], high: Sequence[float],
              share: float = MIN_THICKNESS) -> tuple[list[float], list[float]]:
    """Bounds ``[low, high]`` with every side thinner than ``share`` of the longest widened to
    that, about its middle. A flat scene (a plane, a card, a decal: glTF-Blender-IO's
    39_iridescence.blend is two quads) has no extent across it, and bounds with min equal to max
    there are no box at all; a NeRF draws such a surface as a thin slab, and its grid needs cells
    across it (4 % of the side is about 6 of the 159 vertices the grid grows to).

    Example:
        >>> thickened([-1.0, -0.5, 0.0], [1.0, 0.5, 0.0])
        ([-1.0, -0.5, -0.04], [1.0, 0.5, 0.04])
        >>> thickened([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])  # thick enough: unchanged
        ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    """
    floor = share * max(hi - lo for lo, hi in zip(low, high))
    widened_low, widened_high = [float(value) for value in low], [float(value) for value in high]
    for axis, (lo, hi) in enumerate(zip(low, high)):
        if hi - lo < floor:
            middle = (lo + hi) / 2.0
            widened_low[axis], widened_high[axis] = middle - floor / 2.0, middle + floor / 2.0
    return widened_low, widened_high


def _with_position(matrix: Sequence[Sequence[float]], position: Sequence[float]) -> Matrix4:
    rows = [[float(value) for value in row] for row in matrix]
    for axis in range(3):
        rows[axis][3] = float(position[axis])
    return tuple(tuple(row) for row in rows)  # type: ignore[return-value]


def view_half_angle(intrinsics: Intrinsics) -> float:
    """Narrowest angle (radians) between the optical axis and the image border.

    With lens shift the optical axis (which the protocol aims at the origin) is not the image
    centre, so each side is measured from the principal point.  Raises ValueError when the
    principal point is not inside the image (the object could not be framed at all).
    """
    horizontal = min(intrinsics.cx, intrinsics.w - intrinsics.cx) / intrinsics.fl_x
    vertical = min(intrinsics.cy, intrinsics.h - intrinsics.cy) / intrinsics.fl_y
    tangent = min(horizontal, vertical)
    if tangent <= 0.0:
        raise ValueError(
            f"lens shift puts the principal point ({intrinsics.cx:g}, {intrinsics.cy:g}) outside the "
            f"{intrinsics.w}x{intrinsics.h} image: the protocol's cameras could not see the object"
        )
    return math.atan(tangent)


def fit_target_radius(intrinsics: Intrinsics, margin: float = FIT_MARGIN) -> float:
    """Radius of the NeRF-frame sphere that fits every protocol view with `margin` to spare.

    A sphere of radius R seen from distance D subtends asin(R / D): it stays inside a view whose
    narrowest half-angle is a when R <= D sin(a).  The protocol camera gives R = 1.229.
    """
    if not 0.0 <= margin < 1.0:
        raise ValueError(f"margin must be in [0, 1), got {margin}")
    return (1.0 - margin) * RIG_RADIUS * math.sin(view_half_angle(intrinsics))


def fit_similarity(centre: Sequence[float], radius: float, target_radius: float) -> Similarity:
    """The similarity moving the sphere (centre, radius) to the origin with radius `target_radius`."""
    if not (radius > 0.0 and math.isfinite(radius)):
        raise ValueError(f"the geometry has no extent (bounding sphere radius {radius})")
    scale = target_radius / radius
    return Similarity(scale, (-scale * centre[0], -scale * centre[1], -scale * centre[2]))


def bounding_sphere_radius(centre: Sequence[float], points: Sequence[float]) -> float:
    """Largest distance from `centre` to the points given flat as x0, y0, z0, x1, ..."""
    cx, cy, cz = centre[0], centre[1], centre[2]
    largest = 0.0
    for start in range(0, len(points), 3):
        dx, dy, dz = points[start] - cx, points[start + 1] - cy, points[start + 2] - cz
        squared = dx * dx + dy * dy + dz * dz
        if squared > largest:
            largest = squared
    return math.sqrt(largest)
