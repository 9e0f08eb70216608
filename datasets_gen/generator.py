"""Render a nerf_synthetic-style dataset from the demo scene or a .blend: the one entry point.

Both command lines (`python -m datasets_gen`, `blender -b --python datasets_gen/generate.py`)
and, later, the add-on call `generate_dataset`.  Order of work: validate, prepare the folder,
build or open the scene, force the protocol's render settings, render every view (each image
written atomically), then write the JSON files, each atomically, last.
"""

from __future__ import annotations

import os
import sys
from typing import Any, Optional

from . import trajectories
from .dataset_json import frame_entry, scene_profile, transforms_document
from .options import SPLITS, DatasetGenError, GeneratorOptions
from .output_dir import (
    check_output_dir,
    prepare_output_dir,
    remove_stale_frames,
    temporary_path,
    write_json_atomic,
)
from .progress import ViewProgress

GENERATOR_NAME = "datasets_gen"
GENERATOR_VERSION = 1


def generate_dataset(
    out_dir: str,
    *,
    demo: bool = False,
    blend_path: Optional[str] = None,
    train_views: int = 100,
    val_views: int = 100,
    test_views: int = 200,
    width: int = 800,
    height: int = 800,
    samples: int = 128,
    seed: int = 0,
    full_sphere: bool = False,
    device: str = "CPU",
    overwrite: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """Render a dataset into `out_dir`; return the scene profile it wrote.

    Give exactly one of `demo=True` or `blend_path`.  Note: opening `blend_path` replaces the
    current Blender session's file, and the demo adds a scene to the current file.
    Raises DatasetGenError for bad input.
    """
    options = GeneratorOptions(
        out_dir=out_dir,
        demo=demo,
        blend_path=blend_path,
        train_views=train_views,
        val_views=val_views,
        test_views=test_views,
        width=width,
        height=height,
        samples=samples,
        seed=seed,
        full_sphere=full_sphere,
        device=device,
        overwrite=overwrite,
    )
    return run(options, progress=progress)


def split_poses(options: GeneratorOptions, split: str) -> list[trajectories.RigPose]:
    """The rig poses of one split: random (hemisphere or sphere) for train/val, the spiral for test."""
    count = options.views(split)
    if split == "test":
        return trajectories.test_spiral_poses(count)
    rng = trajectories.split_rng(options.seed, split)
    return trajectories.hemisphere_poses(count, rng, full_sphere=options.full_sphere)


def run(options: GeneratorOptions, progress: bool = True) -> dict[str, Any]:
    """Generate the dataset described by `options`, validating them first (see generate_dataset)."""
    options.validate()
    out_dir = os.path.abspath(options.out_dir)
    check_output_dir(out_dir, options.overwrite)

    # bpy-facing modules are imported only now, so bad input is reported without waiting for Blender.
    try:
        from .blender_render import (
            add_dataset_camera,
            configure_render,
            place_camera,
            render_settings_record,
            render_still,
            scene_camera_intrinsics,
        )
        from .scene_bounds import scene_bounds
    except ModuleNotFoundError as error:
        if error.name not in ("bpy", "bmesh", "mathutils"):
            raise
        raise DatasetGenError(
            "this Python has no Blender module (bpy): install it (pip install bpy) "
            "or run `blender -b --python datasets_gen/generate.py -- ...`"
        ) from None

    scene = _load_scene(options)
    configure_render(
        scene,
        width=options.width,
        height=options.height,
        samples=options.samples,
        seed=options.seed,
        device=options.device,
    )
    add_dataset_camera(scene)
    intrinsics = scene_camera_intrinsics(scene)
    profile = scene_profile(options.scene_source, *scene_bounds(scene))
    generator = _generator_record(options, render_settings_record(scene))
    # Only now, once the scene is known to be usable, is anything created on disk.
    prepare_output_dir(out_dir, SPLITS, options.overwrite)

    documents: dict[str, dict] = {}
    total = sum(options.views(split) for split in SPLITS)
    with ViewProgress(total, enabled=progress) as bar:
        for split in SPLITS:
            poses = split_poses(options, split)
            rotation = trajectories.rotation_step(len(poses))
            frames = []
            for index, pose in enumerate(poses):
                matrix = place_camera(scene, pose.matrix)
                final_path = os.path.join(out_dir, split, f"r_{index}.png")
                partial_path = temporary_path(final_path)
                try:
                    render_still(scene, partial_path)
                    os.replace(partial_path, final_path)
                finally:
                    if os.path.exists(partial_path):
                        os.remove(partial_path)
                frames.append(frame_entry(split, index, rotation, matrix))
                bar.advance(split, index)
            remove_stale_frames(os.path.join(out_dir, split), len(poses))
            documents[split] = transforms_document(intrinsics, frames, generator)

    for split in SPLITS:
        write_json_atomic(os.path.join(out_dir, f"transforms_{split}.json"), documents[split])
    write_json_atomic(os.path.join(out_dir, "scene_profile.json"), profile)
    return profile


def _load_scene(options: GeneratorOptions) -> Any:
    """The scene to render: a freshly built demo scene, or the active scene of the .blend."""
    import bpy

    if options.demo:
        from .demo_scene import build_demo_scene

        return build_demo_scene()
    path = os.path.abspath(str(options.blend_path))
    try:
        bpy.ops.wm.open_mainfile(filepath=path)
    except RuntimeError as error:
        reason = str(error).strip().splitlines()[-1].removeprefix("Error: ")
        raise DatasetGenError(f"cannot open {path}: {reason}") from None
    print(
        f"{GENERATOR_NAME}: note: {path} is rendered as it is (not recentred or rescaled); "
        "it should fit inside radius ~1.4 around the origin for the protocol's cameras",
        file=sys.stderr,
    )
    return bpy.context.scene


def _generator_record(options: GeneratorOptions, render_settings: dict[str, Any]) -> dict[str, Any]:
    """Every setting of the run, so a dataset can be reproduced and audited."""
    record: dict[str, Any] = {
        "name": GENERATOR_NAME,
        "version": GENERATOR_VERSION,
        "scene_source": options.scene_source,
        "seed": options.seed,
        "views": {split: options.views(split) for split in SPLITS},
        "train_val_trajectory": "sphere" if options.full_sphere else "hemisphere",
        "test_trajectory": "spiral: two turns, tilt (cos(360deg*i/n)+1)/2*0.7 rad, azimuth 720deg*i/n",
        "rig": {
            "camera_offset_in_empty": list(trajectories.RIG_CAMERA_OFFSET),
            "radius": trajectories.RIG_RADIUS,
            "empty_euler": "XYZ = (tilt, 0, azimuth); Track-To -Z forward, +Y up",
        },
        "pose_random_streams": "random.Random('datasets_gen/<seed>/<split>'), u then v per view",
        "pixel_convention": "cx, cy from the top-left corner, x right, y down; pixel centres at i + 0.5",
    }
    record.update(render_settings)
    return record
