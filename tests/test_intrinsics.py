"""Pixel intrinsics of a Blender camera (datasets_gen.core.intrinsics), against known values.

The same formulas are checked against real Cycles renders in test_datasets_gen.py.
"""

from __future__ import annotations

import math

import pytest

from datasets_gen.core.intrinsics import camera_intrinsics, render_size


def protocol_camera(**overrides):
    settings = dict(
        lens_mm=50.0,
        sensor_width_mm=36.0,
        sensor_height_mm=24.0,
        sensor_fit="AUTO",
        resolution_x=800,
        resolution_y=800,
    )
    settings.update(overrides)
    return camera_intrinsics(**settings)


def test_protocol_camera_800_square() -> None:
    k = protocol_camera()
    assert (k.w, k.h) == (800, 800)
    assert k.fl_x == pytest.approx(1111.111, abs=1e-3)
    assert k.fl_y == pytest.approx(1111.111, abs=1e-3)
    assert k.camera_angle_x == pytest.approx(0.6911112, abs=1e-7)
    assert k.camera_angle_y == pytest.approx(0.6911112, abs=1e-7)
    assert (k.cx, k.cy) == (400.0, 400.0)


def test_landscape_shift_measured_case() -> None:
    """PROTOCOL.md's measured render: 800x600, shift (0.1, 0.05), AUTO -> principal point (320, 340)."""
    k = protocol_camera(resolution_x=800, resolution_y=600, shift_x=0.1, shift_y=0.05)
    assert (k.cx, k.cy) == (pytest.approx(320.0), pytest.approx(340.0))
    assert k.fl_x == pytest.approx(1111.111, abs=1e-3) and k.fl_y == pytest.approx(k.fl_x)
    assert k.camera_angle_x == pytest.approx(0.6911112, abs=1e-7)
    assert k.camera_angle_y == pytest.approx(2 * math.atan(300 / k.fl_y))


def test_portrait_auto_fits_vertically_with_sensor_width() -> None:
    """AUTO on a portrait image spans sensor_width over the height: the horizontal FOV shrinks."""
    k = protocol_camera(resolution_x=600, resolution_y=800, shift_x=0.1, shift_y=0.05)
    assert k.fl_y == pytest.approx(50 / 36 * 800) and k.fl_x == pytest.approx(k.fl_y)
    assert k.camera_angle_y == pytest.approx(0.6911112, abs=1e-7)
    assert k.camera_angle_x == pytest.approx(2 * math.atan(300 / k.fl_x))
    assert k.camera_angle_x < 0.6911112  # Camera.angle_x would be wrong here
    # Shift is measured in units of the fitted dimension (the height here).
    assert (k.cx, k.cy) == (pytest.approx(300 - 80.0), pytest.approx(400 + 40.0))


def test_vertical_fit_uses_sensor_height() -> None:
    k = protocol_camera(sensor_fit="VERTICAL", resolution_x=800, resolution_y=600, shift_x=0.1, shift_y=-0.05)
    assert k.fl_y == pytest.approx(50 / 24 * 600) and k.fl_x == pytest.approx(k.fl_y)
    assert (k.cx, k.cy) == (pytest.approx(400 - 60.0), pytest.approx(300 - 30.0))


def test_horizontal_fit_on_portrait_uses_width() -> None:
    k = protocol_camera(sensor_fit="HORIZONTAL", resolution_x=600, resolution_y=800, shift_x=0.1, shift_y=0.05)
    assert k.fl_x == pytest.approx(50 / 36 * 600)
    assert (k.cx, k.cy) == (pytest.approx(300 - 60.0), pytest.approx(400 + 30.0))


def test_resolution_percentage_scales_and_floors() -> None:
    half = protocol_camera(resolution_x=1600, resolution_y=1200, resolution_percentage=50, shift_x=0.1, shift_y=0.05)
    full = protocol_camera(resolution_x=800, resolution_y=600, shift_x=0.1, shift_y=0.05)
    assert half == full
    assert render_size(801, 601, 50) == (400, 300)  # Blender's integer arithmetic


def test_pixel_aspect_makes_focal_lengths_differ() -> None:
    """Pixels twice as wide as tall: each covers twice the angle horizontally, so fl_y = 2 fl_x."""
    k = protocol_camera(resolution_x=800, resolution_y=600, pixel_aspect_x=2.0, shift_x=0.1, shift_y=0.05)
    assert k.fl_x == pytest.approx(50 / 36 * 800)
    assert k.fl_y == pytest.approx(2 * k.fl_x)
    assert k.cx == pytest.approx(400 - 80.0)
    assert k.cy == pytest.approx(300 + 0.05 * 800 * 2)


def test_pixel_aspect_can_flip_the_auto_fit() -> None:
    """700x600 with pixels 1.5 times taller than wide is effectively portrait: AUTO fits vertically."""
    k = protocol_camera(resolution_x=700, resolution_y=600, pixel_aspect_y=1.5)
    # The fit dimension is the height in pixel widths: 600 * 1.5 = 900 spans the 36 mm sensor.
    assert k.fl_x == pytest.approx(50 / 36 * 900)
    assert k.fl_y == pytest.approx(k.fl_x / 1.5)


def test_project_uses_top_left_origin_y_down() -> None:
    k = protocol_camera(resolution_x=64, resolution_y=48)
    assert k.project((0.0, 0.0, -3.0)) == (32.0, 24.0)
    u, v = k.project((0.1, 0.1, -3.0))
    assert u > 32.0 and v < 24.0  # right and up in the camera -> right and towards the top row
    with pytest.raises(ValueError):
        k.project((0.0, 0.0, 1.0))


@pytest.mark.parametrize(
    "bad",
    [
        {"sensor_fit": "DIAGONAL"},
        {"lens_mm": 0.0},
        {"pixel_aspect_x": 0.0},
        {"resolution_x": 0},
        {"resolution_percentage": 0},
    ],
)
def test_invalid_camera_settings_raise(bad: dict) -> None:
    with pytest.raises(ValueError):
        protocol_camera(**bad)
