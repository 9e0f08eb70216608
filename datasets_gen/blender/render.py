"""Blender-side rendering for datasets: protocol render settings, the dataset camera, one view.

Settings are forced, not inherited from the .blend, because real files often use EEVEE,
Filmic/AgX, an opaque film or a denoiser, all of which break the nerf_synthetic protocol
(transparent RGBA PNGs, Standard view transform, dither 0).  Every change goes through a
`SettingsJournal`, so the user's open scene is restored afterwards.  `render_settings_record`
reads the values back from Blender so the dataset records what was actually used.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from typing import Any, Iterator, Optional, Sequence

import bpy
from mathutils import Matrix

from ..core.frame_fit import Similarity
from ..core.intrinsics import CameraSettings
from ..core.options import DatasetGenError
from ..io import exr
from ..io.depth_normals import write_depth_normals
from ..io.output_dir import temporary_path
from .scene_state import SettingsJournal, remove_datablock

CAMERA_NAME = "NeRF dataset camera"
GPU_BACKENDS = ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL")
#: Near and far clipping of the dataset camera, in NeRF-frame units (scaled into Blender's).
CLIP_NERF = (0.05, 100.0)


def configure_render(
    scene: "bpy.types.Scene",
    view_layer: "bpy.types.ViewLayer",
    journal: SettingsJournal,
    *,
    camera: CameraSettings,
    samples: int,
    seed: int,
    device: str,
    color_management: str,
    passes: bool,
) -> dict[str, Any]:
    """Apply the protocol's render settings (Cycles, transparent RGBA PNG, Standard); return the device record."""
    render = scene.render
    journal.set(render, "engine", "CYCLES")
    journal.set(render, "resolution_x", camera.resolution_x)
    journal.set(render, "resolution_y", camera.resolution_y)
    journal.set(render, "resolution_percentage", camera.resolution_percentage)
    journal.set(render, "pixel_aspect_x", camera.pixel_aspect_x)
    journal.set(render, "pixel_aspect_y", camera.pixel_aspect_y)
    journal.set(render, "use_border", False)
    journal.set(render, "film_transparent", True)
    journal.set(render, "dither_intensity", 0.0)
    journal.set(render, "use_motion_blur", False)
    journal.set(render, "use_multiview", False)
    # Freestyle lines are drawn in 2D per view: not part of a 3D scene a NeRF can reconstruct.
    journal.set(render, "use_freestyle", False)
    # The compositor and sequencer of a user's file could alter or replace the rendered image.
    journal.set_if_present(render, "use_compositing", False)
    journal.set_if_present(render, "use_sequencer", False)
    # Only the camera moves between views: keep Cycles' scene data (BVH, shaders) across renders.
    journal.set(render, "use_persistent_data", True)
    # A burnt-in stamp would draw text into the views; stamp metadata (date, render time) in the
    # files would make two renders of the same view differ byte for byte.
    for prop in render.bl_rna.properties:
        if prop.identifier.startswith("use_stamp"):
            journal.set(render, prop.identifier, False)

    image = render.image_settings
    journal.snapshot(image, first=("media_type", "file_format"))
    _png_settings(image)

    if color_management == "standard":
        journal.set(scene.display_settings, "display_device", "sRGB")
        view = scene.view_settings
        journal.set(view, "view_transform", "Standard")
        journal.set(view, "look", "None")
        journal.set(view, "exposure", 0.0)
        journal.set(view, "gamma", 1.0)
        journal.set(view, "use_curve_mapping", False)
        journal.set_if_present(view, "use_white_balance", False)

    cycles = scene.cycles
    journal.set(cycles, "samples", samples)
    journal.set(cycles, "seed", seed)
    journal.set(cycles, "use_animated_seed", False)
    journal.set(cycles, "use_denoising", False)
    journal.set(cycles, "film_exposure", 1.0)
    # A per-frame time limit would make the number of samples, and so the pixels, vary.
    journal.set_if_present(cycles, "time_limit", 0.0)

    for layer in scene.view_layers:
        journal.set(layer, "use", layer == view_layer)
    journal.set_if_present(view_layer, "use_pass_combined", True)
    if passes:
        journal.set(view_layer, "use_pass_z", True)
        journal.set(view_layer, "use_pass_normal", True)
    return select_device(scene, journal, device)


def _png_settings(image: "bpy.types.ImageFormatSettings") -> None:
    """8-bit RGBA PNG, colour-managed by the scene's (protocol) settings, not an output override."""
    if hasattr(image, "media_type"):
        image.media_type = "IMAGE"
    image.file_format = "PNG"
    image.color_mode = "RGBA"
    image.color_depth = "8"
    image.compression = 15
    if hasattr(image, "color_management"):
        image.color_management = "FOLLOW_SCENE"


def select_device(scene: "bpy.types.Scene", journal: SettingsJournal, device: str) -> dict[str, Any]:
    """Render on the CPU or on the asked GPU backend ("GPU": the first backend with a device).

    A GPU that is not there is an error, not a silent fallback: a dataset planned for a GPU
    could take a hundred times longer on the CPU.
    """
    if device == "CPU":
        journal.set(scene.cycles, "device", "CPU")
        return {"device": "CPU", "compute_backend": "CPU", "gpus": []}
    preferences = bpy.context.preferences.addons["cycles"].preferences
    backends = GPU_BACKENDS if device == "GPU" else (device,)
    for backend in backends:
        try:
            journal.set(preferences, "compute_device_type", backend)
        except TypeError:  # backend not compiled into this Blender
            continue
        preferences.get_devices()
        gpus = [d for d in preferences.devices if d.type == backend]
        if gpus:
            for gpu in gpus:
                journal.set(gpu, "use", True)
            journal.set(scene.cycles, "device", "GPU")
            return {"device": "GPU", "compute_backend": backend, "gpus": sorted(g.name for g in gpus)}
    raise DatasetGenError(
        f"--device {device}: this Blender's Cycles found no {'GPU' if device == 'GPU' else device} "
        "compute device on this machine (use --device CPU)"
    )


def add_dataset_camera(
    scene: "bpy.types.Scene", journal: SettingsJournal, camera: CameraSettings, frame: Similarity
) -> "bpy.types.Object":
    """A new perspective camera with the dataset's lens, made the scene's camera (removed afterwards).

    A fresh unparented camera keeps a user's camera rig, constraints and animation out of the
    dataset; its matrix_world is set per view from the protocol's rig maths.  Clipping is
    chosen in the NeRF frame and scaled into Blender's units.
    """
    data = bpy.data.cameras.new(CAMERA_NAME)
    journal.on_restore("dataset camera data", remove_datablock(bpy.data.cameras, data))
    data.type = "PERSP"
    data.lens_unit = "MILLIMETERS"
    data.lens = camera.lens_mm
    data.sensor_width = camera.sensor_width_mm
    data.sensor_height = camera.sensor_height_mm
    data.sensor_fit = camera.sensor_fit
    data.shift_x = camera.shift_x
    data.shift_y = camera.shift_y
    data.clip_start = CLIP_NERF[0] / frame.scale
    data.clip_end = CLIP_NERF[1] / frame.scale
    obj = bpy.data.objects.new(CAMERA_NAME, data)
    journal.on_restore("dataset camera", remove_datablock(bpy.data.objects, obj))
    scene.collection.objects.link(obj)
    journal.set(scene, "camera", obj)
    return obj


def read_scene_camera(scene: "bpy.types.Scene") -> CameraSettings:
    """The active camera's lens and the scene's resolution settings (for --use-scene-camera)."""
    camera = scene.camera
    if camera is None or camera.type != "CAMERA":
        raise DatasetGenError(f"--use-scene-camera: scene {scene.name!r} has no active camera")
    return camera_settings(scene, camera, "--use-scene-camera")


def camera_settings(scene: "bpy.types.Scene", camera: "bpy.types.Object", asked_by: str) -> CameraSettings:
    """A perspective camera's lens, sensor and shift as they are now (at the current frame) and
    the scene's resolution settings; ``asked_by`` names the flag in the error for other cameras."""
    data = camera.data
    if data.type != "PERSP":
        raise DatasetGenError(
            f"{asked_by}: camera {camera.name!r} is {data.type.lower()}; only perspective cameras "
            "fit the nerf_synthetic layout"
        )
    render = scene.render
    return CameraSettings(
        lens_mm=float(data.lens),
        sensor_width_mm=float(data.sensor_width),
        sensor_height_mm=float(data.sensor_height),
        sensor_fit=data.sensor_fit,
        shift_x=float(data.shift_x),
        shift_y=float(data.shift_y),
        resolution_x=int(render.resolution_x),
        resolution_y=int(render.resolution_y),
        resolution_percentage=int(render.resolution_percentage),
        pixel_aspect_x=float(render.pixel_aspect_x),
        pixel_aspect_y=float(render.pixel_aspect_y),
    )


def place_camera(scene: "bpy.types.Scene", view_layer: "bpy.types.ViewLayer",
                 matrix: Sequence[Sequence[float]]) -> list[list[float]]:
    """Set the camera's world matrix and return it as Blender holds it (float32, after update)."""
    camera = scene.camera
    camera.matrix_world = Matrix([list(row) for row in matrix])
    view_layer.update()
    return [[float(value) for value in row] for row in camera.matrix_world]


def render_view(
    scene: "bpy.types.Scene",
    view_layer: "bpy.types.ViewLayer",
    paths: dict[str, str],
    depth_normals: Optional[tuple[Sequence[float], float]] = None,
) -> float:
    """Render the camera's view; write the PNG (and depth/normal EXRs); return seconds inside Cycles.

    `depth_normals` = (per-pixel ray length factors, NeRF scale) asks for the EXRs.  Cycles takes
    its depth pass from each pixel's first sample, jittered over the pixel filter, so depth and
    normals come from a second, one-sample render with a 0.01-pixel filter (the ray through the
    pixel centre); alpha comes from the beauty render.  Every file is written under a temporary
    name and moved into place, the PNG last, so a view whose PNG exists is complete.
    """
    png_partial = temporary_path(paths["png"])
    beauty_passes = temporary_path(paths["png"][:-len(".png")] + ".beauty.exr")
    geometry_passes = temporary_path(paths["png"][:-len(".png")] + ".geometry.exr")
    try:
        seconds = _render(scene)
        result = _render_result()
        _save(result, scene, png_partial)
        if depth_normals is not None:
            with _multilayer_exr(scene.render.image_settings):
                _save(result, scene, beauty_passes)
                with _centre_ray_sampling(scene.cycles):
                    seconds += _render(scene)
                _save(_render_result(), scene, geometry_passes)
            _write_depth_normals(view_layer, beauty_passes, geometry_passes, paths, *depth_normals)
        os.replace(png_partial, paths["png"])
    finally:
        for leftover in (png_partial, beauty_passes, geometry_passes):
            if os.path.exists(leftover):
                os.remove(leftover)
    return seconds


def _render(scene: "bpy.types.Scene") -> float:
    """Render the scene's camera view; return the seconds it took."""
    start = time.perf_counter()
    try:
        with _stdout_silenced():
            bpy.ops.render.render(scene=scene.name)
    except RuntimeError as error:
        reason = str(error).strip().splitlines()[-1].removeprefix("Error: ")
        raise DatasetGenError(f"Cycles could not render scene {scene.name!r}: {reason}") from None
    return time.perf_counter() - start


def _render_result() -> "bpy.types.Image":
    result = bpy.data.images.get("Render Result")
    if result is None:
        raise RuntimeError("Blender produced no Render Result")
    return result


def _save(result: "bpy.types.Image", scene: "bpy.types.Scene", path: str) -> None:
    """Save the Render Result exactly at `path` with the scene's image settings.

    Saving the Render Result (instead of `write_still`) avoids Blender's frame-number and
    extension rewriting of the file name.
    """
    with _stdout_silenced():
        result.save_render(filepath=path, scene=scene)
    if not os.path.isfile(path):
        raise RuntimeError(f"Blender did not write {path}")


@contextlib.contextmanager
def _centre_ray_sampling(cycles: Any) -> Iterator[None]:
    """One sample per pixel through the pixel centre (filter width 0.01 px), then back."""
    saved = {name: getattr(cycles, name) for name in ("samples", "filter_width", "use_adaptive_sampling")}
    try:
        cycles.samples = 1
        cycles.filter_width = 0.01
        cycles.use_adaptive_sampling = False
        yield
    finally:
        for name, value in saved.items():
            setattr(cycles, name, value)


def _write_depth_normals(
    view_layer: "bpy.types.ViewLayer",
    beauty_path: str,
    geometry_path: str,
    paths: dict[str, str],
    factors: Sequence[float],
    scale: float,
) -> None:
    """Read the two passes files back and write the dataset's depth and normal EXRs."""
    prefix = view_layer.name
    depth_partial, normal_partial = temporary_path(paths["depth"]), temporary_path(paths["normal"])
    geometry_names = {
        "depth": f"{prefix}.Depth.Z",
        "normal_x": f"{prefix}.Normal.X",
        "normal_y": f"{prefix}.Normal.Y",
        "normal_z": f"{prefix}.Normal.Z",
    }
    try:
        try:
            width, height, beauty = exr.read_channels(beauty_path, [f"{prefix}.Combined.A"])
            _w, _h, geometry = exr.read_channels(geometry_path, list(geometry_names.values()))
        except exr.ExrError as error:
            raise DatasetGenError(
                f"Blender {bpy.app.version_string} wrote render passes this generator cannot read ({error}); "
                "use --depth-normals none"
            ) from None
        passes = {key: geometry[name] for key, name in geometry_names.items()}
        passes["alpha"] = beauty[f"{prefix}.Combined.A"]
        write_depth_normals(depth_partial, normal_partial, width, height, passes, factors, scale)
        os.replace(depth_partial, paths["depth"])
        os.replace(normal_partial, paths["normal"])
    finally:
        for leftover in (depth_partial, normal_partial):
            if os.path.exists(leftover):
                os.remove(leftover)


@contextlib.contextmanager
def _multilayer_exr(image: "bpy.types.ImageFormatSettings") -> Iterator[None]:
    """Temporarily save 32-bit uncompressed multilayer EXRs (all passes), which `exr` can read."""
    try:
        if hasattr(image, "media_type"):
            image.media_type = "MULTI_LAYER_IMAGE"
        image.file_format = "OPEN_EXR_MULTILAYER"
        image.color_depth = "32"
        image.exr_codec = "NONE"
        yield
    finally:
        _png_settings(image)


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


def render_settings_record(scene: "bpy.types.Scene", device: dict[str, Any]) -> dict[str, Any]:
    """The render settings as Blender reports them, for the dataset's `generator` record."""
    render = scene.render
    cycles = scene.cycles
    view = scene.view_settings
    camera = scene.camera.data
    return {
        "blender_version": bpy.app.version_string,
        "engine": render.engine,
        "device": cycles.device,
        "compute_backend": device["compute_backend"],
        "gpus": device["gpus"],
        "samples": cycles.samples,
        "cycles_seed": cycles.seed,
        "denoising": bool(cycles.use_denoising),
        "adaptive_sampling": bool(cycles.use_adaptive_sampling),
        "adaptive_threshold": cycles.adaptive_threshold,
        "max_bounces": cycles.max_bounces,
        "light_paths": {
            name: getattr(cycles, name)
            for name in ("diffuse_bounces", "glossy_bounces", "transmission_bounces", "volume_bounces",
                         "transparent_max_bounces", "sample_clamp_direct", "sample_clamp_indirect",
                         "caustics_reflective", "caustics_refractive", "film_transparent_glass")
            if hasattr(cycles, name)
        },
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
