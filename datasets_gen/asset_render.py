"""`datasets_gen --render-asset ASSET.glb --dataset DATASET --out DIR [--engine cycles|eevee]`: a
baked NeRF asset (the backend's `export`) rendered by Blender from the dataset's test cameras as
its views were rendered (the same lens, size, samples and seed, transparent film, the same colour
management), into ``DIR/STEM.png``, one for each view, named as the dataset names them: what
``python -m nerf_backend eval --dataset DATASET --renders DIR`` scores against Cycles' ground
truth.

The asset is imported into an empty scene (nothing else to light or hide it: its material is
unlit, the lighting is in its texture), so the renders show the asset alone, as the NeRF's own
renders show the NeRF alone; with nothing lit, EEVEE renders it without shadows.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

from nerf_contract.run_layout import ASSET_ENGINES, ASSET_RENDER_RECORD

from .core.frame_fit import Similarity
from .core.intrinsics import CameraSettings
from .core.options import DatasetGenError
from .core.progress import ViewProgress
from .io.split_document import read_split_document


def dataset_camera(generator: dict[str, Any]) -> CameraSettings:
    """The camera the dataset's views were rendered with, from its generator record."""
    lens = generator["camera"]
    width, height = generator["resolution"]
    aspect_x, aspect_y = generator.get("pixel_aspect", (1.0, 1.0))
    return CameraSettings(lens_mm=lens["lens_mm"], sensor_width_mm=lens["sensor_width_mm"],
                          sensor_height_mm=lens["sensor_height_mm"], sensor_fit=lens["sensor_fit"],
                          shift_x=lens["shift"][0], shift_y=lens["shift"][1], resolution_x=width, resolution_y=height,
                          resolution_percentage=generator.get("resolution_percentage", 100),
                          pixel_aspect_x=aspect_x, pixel_aspect_y=aspect_y)


def render_asset(asset: str, dataset_dir: str, out_dir: str, engine: str = "cycles", split: str = "test",
                 device: str = "CPU", progress: bool = True) -> dict[str, Any]:
    """Render ``asset`` from every camera of the dataset's ``split`` with ``engine`` into
    ``out_dir``; returns the record also written as ``out_dir/asset_render.json``. Replaces the
    open Blender file with an empty one. DatasetGenError for bad input."""
    from .generator import blender_journal

    journal = blender_journal()  # the clear error when this Python has no bpy
    if engine not in ASSET_ENGINES:
        raise DatasetGenError(f"--engine {engine}: one of {', '.join(ASSET_ENGINES)}")
    if not os.path.isfile(asset):
        raise DatasetGenError(f"{asset}: no such asset (python -m nerf_backend export RUN --out ASSET.glb makes one)")
    record = read_split_document(dataset_dir, split, ("world_to_nerf", "generator", "frames"),
                                 "--render-asset renders the cameras of a dataset written by datasets_gen")
    import bpy

    from .blender.compat import set_eevee
    from .blender.render import add_dataset_camera, configure_render, place_camera, render_view

    bpy.ops.wm.read_factory_settings(use_empty=True)
    try:
        bpy.ops.import_scene.gltf(filepath=os.path.abspath(asset))
    except RuntimeError as error:
        raise DatasetGenError(f"{asset}: Blender's glTF importer refused it ({str(error).strip()})") from None
    scene, view_layer = bpy.context.scene, bpy.context.view_layer
    generator = record["generator"]
    camera = dataset_camera(generator)
    similarity = Similarity(float(record["world_to_nerf"]["scale"]),
                            tuple(float(v) for v in record["world_to_nerf"]["translation"]))
    device_record = configure_render(scene, view_layer, journal, camera=camera, samples=int(generator["samples"]),
                                     seed=int(generator.get("cycles_seed", 0)), device=device,
                                     color_management=generator.get("color_management", "standard"), passes=False)
    if engine == "eevee":
        set_eevee(scene, journal)
        # The asset is unlit and the scene holds no light: shadows change no pixel, yet EEVEE's
        # shadow maps took 93 % of its time (A.blend's asset, 48×48, 3 views: 67 s with them,
        # 5.3 s without, the same bytes). Blender before 4.2 has no such switch.
        if hasattr(scene.eevee, "use_shadows"):
            journal.set(scene.eevee, "use_shadows", False)
    add_dataset_camera(scene, journal, camera, similarity)
    os.makedirs(out_dir, exist_ok=True)
    written, started = [], time.perf_counter()
    with ViewProgress(len(record["frames"]), enabled=progress, desc=f"{engine} renders of the asset") as bar:
        for index, frame in enumerate(record["frames"]):
            place_camera(scene, view_layer, similarity.camera_to_blender(frame["transform_matrix"]))
            stem = os.path.splitext(os.path.basename(frame.get("file_path") or f"r_{index}"))[0]
            path = os.path.join(out_dir, stem + ".png")
            render_view(scene, view_layer, {"png": path})
            written.append(path)
            bar.advance_named(stem)
    result = {"asset": os.path.abspath(asset), "dataset": os.path.abspath(dataset_dir), "split": split,
              "engine": engine, "render_engine": scene.render.engine, "blender_version": bpy.app.version_string,
              "views": len(written), "seconds": round(time.perf_counter() - started, 3),
              "samples": int(generator["samples"]) if engine == "cycles" else None, "device": device_record,
              "color_management": generator.get("color_management", "standard")}
    with open(os.path.join(out_dir, ASSET_RENDER_RECORD), "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=1)
    journal.restore()
    return result
