"""Blender-side camera paths: a camera's evaluated pose and lens at each frame, and Cycles'
renders of those frames with a dataset's settings (camera_path.py holds the pure maths)."""

from __future__ import annotations

import os
from typing import Any, Iterable

import bpy

from ..core.camera_path import FrameCamera, frame_stem
from ..core.options import DatasetGenError
from ..core.progress import ViewProgress
from .render import camera_settings, configure_render, render_view
from .scene_state import SettingsJournal

FLAG = "--camera-path"


def find_camera(camera_name: str) -> "bpy.types.Object":
    """The camera object named ``camera_name`` (DatasetGenError naming the cameras there are)."""
    camera = bpy.data.objects.get(camera_name)
    if camera is None or camera.type != "CAMERA":
        cameras = sorted(obj.name for obj in bpy.data.objects if obj.type == "CAMERA")
        raise DatasetGenError(f"{FLAG} {camera_name!r}: no camera object of that name in "
                              f"{bpy.data.filepath or 'the open scene'} (cameras: {', '.join(cameras) or 'none'})")
    return camera


def scene_frame_rate(scene: "bpy.types.Scene") -> float:
    """Frames per second as Blender plays them (fps / fps_base, e.g. 30000/1001)."""
    return float(scene.render.fps) / float(scene.render.fps_base)


def read_camera_frames(scene: "bpy.types.Scene", camera: "bpy.types.Object", frames: Iterable[int]) -> list[FrameCamera]:
    """The camera at each frame as Blender evaluates it (parents, constraints, drivers and an
    animated lens included); the scene's current frame is restored afterwards."""
    current = scene.frame_current, scene.frame_subframe
    result = []
    try:
        for frame in frames:
            scene.frame_set(frame)
            matrix = [[float(value) for value in row] for row in camera.matrix_world]
            result.append(FrameCamera(frame, matrix, camera_settings(scene, camera, FLAG)))
    finally:
        scene.frame_set(current[0], subframe=current[1])
    return result


def render_cycles_frames(
    scene: "bpy.types.Scene", view_layer: "bpy.types.ViewLayer", camera: "bpy.types.Object",
    frames: list[FrameCamera], out_dir: str, generator: dict[str, Any], device: str, progress: bool,
) -> int:
    """Render each frame's missing ``STEM.png`` into ``out_dir`` with Cycles as the dataset was
    rendered (its samples, seed and colour management; the protocol's film and PNG), through
    the camera itself; return how many were rendered. Frames already there are kept (resume)."""
    os.makedirs(out_dir, exist_ok=True)
    todo = [frame for frame in frames
            if not os.path.isfile(os.path.join(out_dir, f"{frame_stem(frame.frame)}.png"))]
    if not todo:
        return 0
    journal = SettingsJournal()
    current = scene.frame_current, scene.frame_subframe
    try:
        configure_render(scene, view_layer, journal, camera=frames[0].camera,
                         samples=int(generator.get("samples", 128)), seed=int(generator.get("cycles_seed", 0)),
                         device=device, color_management=generator.get("color_management", "standard"),
                         passes=False)
        journal.set(scene, "camera", camera)
        with ViewProgress(len(todo), enabled=progress, unit="frame") as bar:
            for frame in todo:
                scene.frame_set(frame.frame)
                path = os.path.join(out_dir, f"{frame_stem(frame.frame)}.png")
                try:
                    # The render operator takes the frame's animation from the context's scene: a
                    # scene that is not the window's (a built-in one) would render frame 1's poses.
                    with bpy.context.temp_override(scene=scene, view_layer=view_layer):
                        render_view(scene, view_layer, {"png": path})
                except OSError as error:
                    raise DatasetGenError(f"cannot write {error.filename or path}: {error.strerror}") from None
                bar.advance_named(f"frame {frame.frame}")
    finally:
        scene.frame_set(current[0], subframe=current[1])
        journal.restore()
    return len(todo)

