"""`datasets_gen --camera-path CAMERA [--frames S:E[:STEP]] [--with-cycles] --out DATASET`: a
camera's animation as a camera path in DATASET's NeRF frame, for
`python -m nerf_backend render RUN --camera-path`, and (``--with-cycles``) the same frames
rendered by Cycles with the dataset's settings, to compare the NeRF with frame by frame.

Written into ``DATASET/camera_paths/CAMERA/``: ``camera_path.json`` and ``cycles/STEM.png``.
Rerunning keeps the Cycles frames already rendered; a path whose poses or lens changed since
is refused unless ``overwrite`` (its Cycles frames would no longer match it).
"""

from __future__ import annotations

import json
import os
import shutil
from typing import Any, Optional, Sequence

from nerf_contract.dataset_layout import CAMERA_PATH_NAME, CYCLES_FRAMES_DIR, camera_path_folder

from .core.camera_path import camera_path_document, parse_frames
from .core.options import DatasetGenError, GeneratorOptions
from .io.output_dir import write_json_atomic
from .io.split_document import read_split_document


def dataset_record(dataset_dir: str) -> dict[str, Any]:
    """The dataset's transforms_train.json (its world_to_nerf and generator settings)."""
    return read_split_document(dataset_dir, "train", ("world_to_nerf",),
                               "a camera path is mapped into a dataset's NeRF frame: generate the dataset first "
                               "(the same command without --camera-path)")


def path_folder(dataset_dir: str, camera_name: str) -> str:
    return os.path.join(dataset_dir, camera_path_folder(camera_name))


def export_camera_path(
    dataset_dir: str, camera_name: str, frames: Optional[Sequence[int] | str] = None, *, scene: Any = None,
    cycles: bool = False, out_dir: Optional[str] = None, overwrite: bool = False, device: str = "CPU",
    progress: bool = True, resolution_percentage: Optional[int] = None,
) -> str:
    """Write the camera path of ``camera_name`` over ``frames`` (``"S:E[:STEP]"`` or frame
    numbers; default: the scene's frame range) from ``scene`` (default: the open one) and,
    with ``cycles``, Cycles' frames; return the JSON's path. The frames have the scene's
    render size, scaled by ``resolution_percentage`` when given (as Blender's own percentage
    does; the scene keeps its own). DatasetGenError for bad input."""
    from .generator import blender_journal

    blender_journal()  # the clear error when this Python has no bpy
    import bpy

    from .blender.camera_animation import find_camera

    dataset_dir = os.path.abspath(dataset_dir)
    record = dataset_record(dataset_dir)
    scene = scene if scene is not None else bpy.context.scene
    if frames is None:
        frames = range(scene.frame_start, scene.frame_end + 1, max(1, scene.frame_step))
    elif isinstance(frames, str):
        frames = parse_frames(frames)
    camera = find_camera(camera_name)
    journal = blender_journal()
    try:
        if resolution_percentage is not None:
            journal.set(scene.render, "resolution_percentage", resolution_percentage)
        return _export(scene, camera, frames, record, dataset_dir, cycles, out_dir, overwrite, device, progress)
    finally:
        journal.restore()


def _export(scene: Any, camera: Any, frames: Sequence[int], record: dict[str, Any], dataset_dir: str, cycles: bool,
            out_dir: Optional[str], overwrite: bool, device: str, progress: bool) -> str:
    from .blender.camera_animation import read_camera_frames, render_cycles_frames, scene_frame_rate
    from .blender.scene_bounds import render_view_layer

    camera_frames = read_camera_frames(scene, camera, frames)
    document = camera_path_document(camera.name, camera_frames, record["world_to_nerf"], scene_frame_rate(scene),
                                    cycles=cycles, dataset=dataset_dir)
    out_dir = os.path.abspath(out_dir or path_folder(dataset_dir, camera.name))
    path = os.path.join(out_dir, CAMERA_PATH_NAME)
    _refuse_changed_path(path, document, overwrite)
    os.makedirs(out_dir, exist_ok=True)
    write_json_atomic(path, document)
    if cycles:
        from .generator import GENERATOR_NAME

        rendered = render_cycles_frames(scene, render_view_layer(scene), camera, camera_frames,
                                        os.path.join(out_dir, CYCLES_FRAMES_DIR), record.get("generator", {}), device,
                                        progress)
        kept = len(camera_frames) - rendered
        if kept:
            print(f"{GENERATOR_NAME}: kept {kept} Cycles frames already rendered", flush=True)
    return path


def export_from_options(options: GeneratorOptions, camera_name: str, frames: Optional[str], cycles: bool,
                        progress: bool, resolution_percentage: Optional[int] = None) -> str:
    """The command line's --camera-path: load the scene the options name, then export."""
    from .generator import blender_journal, load_scene

    blender_journal()
    scene, _ = load_scene(options, None)
    return export_camera_path(options.out_dir, camera_name, frames, scene=scene, cycles=cycles,
                              overwrite=options.overwrite, device=options.device, progress=progress,
                              resolution_percentage=resolution_percentage)


def _refuse_changed_path(path: str, document: dict[str, Any], overwrite: bool) -> None:
    """An earlier path in the same folder must match, or be replaced on request with its frames."""
    if not os.path.isfile(path):
        return
    try:
        with open(path, encoding="utf-8") as handle:
            earlier = json.load(handle)
    except (OSError, ValueError):
        earlier = None
    same = isinstance(earlier, dict) and _comparable(earlier) == _comparable(document)
    if same:
        return
    if not overwrite:
        raise DatasetGenError(f"{path}: a different camera path is there (the camera's animation, lens or frames "
                              "changed); pass --overwrite to replace "
                              "it and its Cycles frames")
    cycles_dir = os.path.join(os.path.dirname(path), CYCLES_FRAMES_DIR)
    if os.path.isdir(cycles_dir):
        shutil.rmtree(cycles_dir)


def _comparable(document: dict[str, Any]) -> Any:
    """What decides the frames' pixels: poses and intrinsics rounded past float32 noise."""
    def rounded(value: Any) -> Any:
        if isinstance(value, float):
            return round(value, 5)
        if isinstance(value, list):
            return [rounded(item) for item in value]
        if isinstance(value, dict):
            return {key: rounded(item) for key, item in value.items()}
        return value
    frames = [{key: value for key, value in frame.items() if key != "cycles_file_path"}
              for frame in document.get("frames") or [] if isinstance(frame, dict)]
    return rounded({"frames": frames, "world_to_nerf": document.get("world_to_nerf")})
