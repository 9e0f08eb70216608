"""Blender-side rendering for datasets: protocol render settings, the dataset camera, one view.

Settings are forced, not inherited from the .blend, because real files often use EEVEE,
Filmic/AgX, an opaque film or a denoiser, all of which break the nerf_synthetic protocol
(transparent RGBA PNGs, Standard view transform, dither 0). `render_settings_record` reads
the values back from Blender so the dataset records what was actually used.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any, Iterator, Sequence

import bpy
from mathutils import Matrix

from .blender_compat import set_if_present
from .intrinsics import Intrinsics, camera_intrinsics
from .options import DatasetGenError

CAMERA_NAME = "NeRF dataset camera"
LENS_MM = 50.0
SENSOR_WIDTH_MM = 36.0
SENSOR_HEIGHT_MM = 24.0
GPU_BACKENDS = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")


def configure_render(
    scene: "bpy.types.Scene", *, width: int, height: int, samples: int, seed: int, device: str
) -> None:
    """Apply the protocol's render settings to `scene` (Cycles, transparent RGBA PNG, Standard)."""
    render = scene.render
    render.engine = "CYCLES"
    render.resolution_x = width
    render.resolution_y = height
    render.resolution_percentage = 100
    render.pixel_aspect_x = 1.0
    render.pixel_aspect_y = 1.0
    render.use_border = False
    render.film_transparent = True
    render.dither_intensity = 0.0
    render.use_motion_blur = False
    # The compositor and sequencer of a user's file could alter or replace the rendered image.
    set_if_present(render, "use_compositing", False)
    set_if_present(render, "use_sequencer", False)
    # Only the camera moves between views: keep Cycles' scene data (BVH, shaders) across renders.
    render.use_persistent_data = True

    image = render.image_settings
    set_if_present(image, "media_type", "IMAGE")
    image.file_format = "PNG"
    image.color_mode = "RGBA"
    image.color_depth = "8"
    image.compression = 15

    scene.display_settings.display_device = "sRGB"
    view = scene.view_settings
    view.view_transform = "Standard"
    view.look = "None"
    view.exposure = 0.0
    view.gamma = 1.0
    view.use_curve_mapping = False
    set_if_present(view, "use_white_balance", False)

    cycles = scene.cycles
    cycles.samples = samples
    cycles.seed = seed
    cycles.use_animated_seed = False
    cycles.use_denoising = False
    cycles.film_exposure = 1.0
    _select_device(scene, device)


def _select_device(scene: "bpy.types.Scene", device: str) -> None:
    """Render on the CPU, or on the first GPU backend Cycles finds devices for."""
    if device == "CPU":
        scene.cycles.device = "CPU"
        return
    preferences = bpy.context.preferences.addons["cycles"].preferences
    for backend in GPU_BACKENDS:
        try:
            preferences.compute_device_type = backend
        except TypeError:  # backend not compiled into this Blender
            continue
        preferences.get_devices()
        gpus = [d for d in preferences.devices if d.type == backend]
        if gpus:
            for gpu in gpus:
                gpu.use = True
            scene.cycles.device = "GPU"
            return
    raise DatasetGenError("--device GPU: Cycles found no GPU compute device (use --device CPU)")


def add_dataset_camera(scene: "bpy.types.Scene") -> "bpy.types.Object":
    """A new 50 mm / 36 mm (sensor fit AUTO) camera, made the scene's camera.

    A fresh unparented camera keeps a user's camera rig, constraints and lens out of the dataset;
    its matrix_world is set per view from the protocol's rig maths.
    """
    data = bpy.data.cameras.new(CAMERA_NAME)
    data.type = "PERSP"
    data.lens_unit = "MILLIMETERS"
    data.lens = LENS_MM
    data.sensor_width = SENSOR_WIDTH_MM
    data.sensor_height = SENSOR_HEIGHT_MM
    data.sensor_fit = "AUTO"
    data.shift_x = 0.0
    data.shift_y = 0.0
    data.clip_start = 0.05
    data.clip_end = 100.0
    camera = bpy.data.objects.new(CAMERA_NAME, data)
    scene.collection.objects.link(camera)
    scene.camera = camera
    return camera


def scene_camera_intrinsics(scene: "bpy.types.Scene") -> Intrinsics:
    """Pixel intrinsics of the scene's camera with the scene's render settings, read from Blender."""
    data = scene.camera.data
    render = scene.render
    return camera_intrinsics(
        lens_mm=data.lens,
        sensor_width_mm=data.sensor_width,
        sensor_height_mm=data.sensor_height,
        sensor_fit=data.sensor_fit,
        resolution_x=render.resolution_x,
        resolution_y=render.resolution_y,
        resolution_percentage=render.resolution_percentage,
        pixel_aspect_x=render.pixel_aspect_x,
        pixel_aspect_y=render.pixel_aspect_y,
        shift_x=data.shift_x,
        shift_y=data.shift_y,
    )


def place_camera(scene: "bpy.types.Scene", matrix: Sequence[Sequence[float]]) -> list[list[float]]:
    """Set the camera's world matrix and return it as Blender holds it (float32, after update)."""
    camera = scene.camera
    camera.matrix_world = Matrix([list(row) for row in matrix])
    scene.view_layers[0].update()
    return [[float(value) for value in row] for row in camera.matrix_world]


def render_still(scene: "bpy.types.Scene", path: str) -> None:
    """Render the scene's camera view and save it exactly at `path` with the scene's image settings.

    Saving the Render Result (instead of `write_still`) avoids Blender's frame-number and
    extension rewriting of the file name.
    """
    with _stdout_silenced():
        bpy.ops.render.render(scene=scene.name)
    result = bpy.data.images.get("Render Result")
    if result is None:
        raise RuntimeError("Blender produced no Render Result")
    result.save_render(filepath=path, scene=scene)
    if not os.path.isfile(path):
        raise RuntimeError(f"Blender did not write {path}")


@contextlib.contextmanager
def _stdout_silenced() -> Iterator[None]:
    """Drop what Blender prints on stdout (file descriptor 1) meanwhile; stderr is kept.

    A background render prints ~25 status lines per view, which would drown the progress bar.
    """
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no usable stdout descriptor (embedded use): nothing to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def render_settings_record(scene: "bpy.types.Scene") -> dict[str, Any]:
    """The render settings as Blender reports them, for the dataset's `generator` record."""
    render = scene.render
    cycles = scene.cycles
    view = scene.view_settings
    camera = scene.camera.data
    return {
        "blender_version": bpy.app.version_string,
        "engine": render.engine,
        "device": cycles.device,
        "samples": cycles.samples,
        "cycles_seed": cycles.seed,
        "denoising": bool(cycles.use_denoising),
        "adaptive_sampling": bool(cycles.use_adaptive_sampling),
        "adaptive_threshold": cycles.adaptive_threshold,
        "max_bounces": cycles.max_bounces,
        "pixel_filter": {"type": cycles.pixel_filter_type, "width_px": cycles.filter_width},
        "resolution": [render.resolution_x, render.resolution_y],
        "resolution_percentage": render.resolution_percentage,
        "pixel_aspect": [render.pixel_aspect_x, render.pixel_aspect_y],
        "film_transparent": bool(render.film_transparent),
        "dither": render.dither_intensity,
        "display_device": scene.display_settings.display_device,
        "view_transform": view.view_transform,
        "look": view.look,
        "exposure": view.exposure,
        "gamma": view.gamma,
        "image": {
            "file_format": render.image_settings.file_format,
            "color_mode": render.image_settings.color_mode,
            "color_depth": render.image_settings.color_depth,
        },
        "frame": scene.frame_current,
        "camera": {
            "lens_mm": camera.lens,
            "sensor_width_mm": camera.sensor_width,
            "sensor_height_mm": camera.sensor_height,
            "sensor_fit": camera.sensor_fit,
            "shift": [camera.shift_x, camera.shift_y],
            "clip": [camera.clip_start, camera.clip_end],
        },
    }
