"""Pinhole intrinsics (pixels) of a Blender perspective camera, as Cycles renders it.

Why this exists: `Camera.angle_x` is 2*atan(sensor_width / (2*lens)) whatever the sensor fit
and resolution, so exporters that write it as the image's horizontal FOV are wrong for
portrait images, vertical fits, non-square pixels and lens shift.  This follows Blender's
own view-plane computation (BKE_camera_params_compute_viewplane / Cycles' camera sync):

* The "fit" dimension spans the sensor: the image width for a horizontal fit, the image height
  (in units of horizontal pixels: H * pixel_aspect_y / pixel_aspect_x) for a vertical fit.
* AUTO fits horizontally when W * pixel_aspect_x >= H * pixel_aspect_y, and always measures with
  `sensor_width`; HORIZONTAL uses `sensor_width`, VERTICAL uses `sensor_height`.
* Lens shift is in units of that fit dimension; shift +x moves the image window right (so the
  principal point moves left), shift +y moves it up (the principal point moves down in a
  y-down image).

Conventions of the result: pixels, origin at the top-left corner of the image, x right, y DOWN,
pixel i covers [i, i+1) so its centre is at i + 0.5; an unshifted camera has cx = w/2, cy = h/2.
A camera-space point (X, Y, Z) with Z < 0 (Blender camera: looks down -Z, +Y up) projects to
u = cx + fl_x * X / -Z,  v = cy - fl_y * Y / -Z.

Standard library only (no numpy, no bpy) so it runs inside any Blender.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import asdict, dataclass
from typing import Any, Sequence

SENSOR_FITS = ("AUTO", "HORIZONTAL", "VERTICAL")


@dataclass(frozen=True)
class Intrinsics:
    """Pixel intrinsics of a rendered image; field names follow the common transforms.json keys."""

    w: int
    h: int
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    camera_angle_x: float  # true horizontal FOV of the image: 2 * atan(w / (2 * fl_x))
    camera_angle_y: float  # true vertical FOV of the image: 2 * atan(h / (2 * fl_y))

    def as_dict(self) -> dict:
        """Plain dict for JSON."""
        return asdict(self)

    def project(self, point_camera: Sequence[float]) -> tuple[float, float]:
        """Pixel coordinates (x right, y down, centres at i + 0.5) of a camera-space point.

        Raises ValueError for points not in front of the camera (Z >= 0).
        """
        x, y, z = point_camera[0], point_camera[1], point_camera[2]
        if z >= 0.0:
            raise ValueError("point is not in front of the camera (camera looks down -Z)")
        return (self.cx + self.fl_x * x / -z, self.cy - self.fl_y * y / -z)


def render_size(resolution_x: int, resolution_y: int, resolution_percentage: int = 100) -> tuple[int, int]:
    """Rendered image size in pixels: Blender scales with integer arithmetic (floors)."""
    return (resolution_x * resolution_percentage) // 100, (resolution_y * resolution_percentage) // 100


def camera_intrinsics(
    *,
    lens_mm: float,
    sensor_width_mm: float,
    sensor_height_mm: float,
    sensor_fit: str,
    resolution_x: int,
    resolution_y: int,
    resolution_percentage: int = 100,
    pixel_aspect_x: float = 1.0,
    pixel_aspect_y: float = 1.0,
    shift_x: float = 0.0,
    shift_y: float = 0.0,
) -> Intrinsics:
    """Intrinsics of a perspective Blender camera for the given render settings (see module docstring)."""
    if sensor_fit not in SENSOR_FITS:
        raise ValueError(f"sensor_fit must be one of {SENSOR_FITS}, got {sensor_fit!r}")
    if lens_mm <= 0 or sensor_width_mm <= 0 or sensor_height_mm <= 0:
        raise ValueError("lens and sensor sizes must be positive")
    if pixel_aspect_x <= 0 or pixel_aspect_y <= 0:
        raise ValueError("pixel aspect must be positive")
    w, h = render_size(resolution_x, resolution_y, resolution_percentage)
    if w <= 0 or h <= 0:
        raise ValueError(f"render size must be positive, got {w}x{h}")

    # Height of one pixel in units of pixel widths (Blender's "ycor").
    pixel_height_in_widths = pixel_aspect_y / pixel_aspect_x
    if sensor_fit == "AUTO":
        horizontal = w * pixel_aspect_x >= h * pixel_aspect_y
        sensor_mm = sensor_width_mm
    elif sensor_fit == "HORIZONTAL":
        horizontal = True
        sensor_mm = sensor_width_mm
    else:
        horizontal = False
        sensor_mm = sensor_height_mm

    # The fit dimension, in pixel widths, is what the sensor (and lens shift) is measured against.
    fit_size = float(w) if horizontal else h * pixel_height_in_widths
    fl_x = lens_mm * fit_size / sensor_mm
    fl_y = fl_x / pixel_height_in_widths
    cx = w / 2.0 - shift_x * fit_size
    cy = h / 2.0 + shift_y * fit_size / pixel_height_in_widths
    return Intrinsics(
        w=w,
        h=h,
        fl_x=fl_x,
        fl_y=fl_y,
        cx=cx,
        cy=cy,
        camera_angle_x=2.0 * math.atan(w / (2.0 * fl_x)),
        camera_angle_y=2.0 * math.atan(h / (2.0 * fl_y)),
    )


@dataclass(frozen=True)
class CameraSettings:
    """What decides a dataset camera's intrinsics: the Blender camera and render settings.

    The defaults are the protocol's camera (Blender's default camera: 50 mm lens, 36 x 24 mm
    sensor, AUTO fit, no shift) at 800 x 800, 100 %, square pixels.
    """

    lens_mm: float = 50.0
    sensor_width_mm: float = 36.0
    sensor_height_mm: float = 24.0
    sensor_fit: str = "AUTO"
    shift_x: float = 0.0
    shift_y: float = 0.0
    resolution_x: int = 800
    resolution_y: int = 800
    resolution_percentage: int = 100
    pixel_aspect_x: float = 1.0
    pixel_aspect_y: float = 1.0

    def intrinsics(self) -> Intrinsics:
        """The pixel intrinsics these settings render with (ValueError when they are invalid)."""
        return camera_intrinsics(
            lens_mm=self.lens_mm,
            sensor_width_mm=self.sensor_width_mm,
            sensor_height_mm=self.sensor_height_mm,
            sensor_fit=self.sensor_fit,
            resolution_x=self.resolution_x,
            resolution_y=self.resolution_y,
            resolution_percentage=self.resolution_percentage,
            pixel_aspect_x=self.pixel_aspect_x,
            pixel_aspect_y=self.pixel_aspect_y,
            shift_x=self.shift_x,
            shift_y=self.shift_y,
        )

    def record(self) -> dict[str, Any]:
        """Plain dict for the dataset's JSON."""
        return asdict(self)


def ray_length_factors(intrinsics: Intrinsics) -> "array[float]":
    """Per pixel (rows top to bottom), the length of the ray direction whose camera-space depth is 1.

    Blender's depth pass is planar (distance along the optical axis); multiplying it by this
    factor gives the distance from the camera centre along the ray through the pixel centre:
    sqrt(1 + ((u - cx) / fl_x)^2 + ((v - cy) / fl_y)^2) with u, v = column + 0.5, row + 0.5.
    """
    xs = [((column + 0.5 - intrinsics.cx) / intrinsics.fl_x) ** 2 for column in range(intrinsics.w)]
    factors = array("d")
    for row in range(intrinsics.h):
        y2 = ((row + 0.5 - intrinsics.cy) / intrinsics.fl_y) ** 2
        factors.extend(math.sqrt(1.0 + x2 + y2) for x2 in xs)
    return factors
