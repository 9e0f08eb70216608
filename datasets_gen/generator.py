"""Render a nerf_synthetic-style dataset from a built-in scene, a .blend or the open scene.

Both command lines (`python -m datasets_gen`, `blender -b --python datasets_gen/generate.py`),
`generate_dataset` and the add-on call `run`, with GeneratorOptions.  Order of work: validate,
check the output folder, load the scene, check it (refusing before anything is written),
fit it into the protocol's frame, voxelise it (the occupancy prior, written before the views),
force the protocol's render settings (undone afterwards), then render every view (each file
written atomically, already-verified views skipped with --resume, other shards' views skipped
with --shard) and write the JSON files last, atomically.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

from nerf_contract.dataset_layout import APPEARANCE_REGIONS, GEOMETRY_NAME, PRIOR_NAME, PROFILE_NAME, SPLITS

from .core import trajectories
from .core.builtin_scenes import builtin_scene
from .core.frame_fit import (
    BLENDER_RULE,
    DEMO_RULE,
    FIT_MARGIN,
    FIT_RULE,
    IDENTITY,
    Similarity,
    fit_similarity,
    fit_target_radius,
    thickened,
    view_half_angle,
)
from .core.intrinsics import CameraSettings, Intrinsics, ray_length_factors
from .core.materials import classify_material
from .core.options import DatasetGenError, GeneratorOptions, options_from_keywords, validate_camera
from .core.progress import ViewProgress
from .core.scene_checks import CheckOutcome, SceneFacts, evaluate
from .io.dataset_json import frame_entry, scene_profile, transforms_document
from .io.depth_normals import DEPTH_CHANNELS, LAYOUT_RECORD, NORMAL_CHANNELS
from .io.exr import ExrError, check_file
from .io.formats import write_formats
from .io.output_dir import (
    check_output_dir,
    finish_run,
    prepare_output_dir,
    recorded_settings,
    remove_stale_frames,
    require_same_settings,
    sibling_shard_settings,
    transforms_name,
    view_paths,
    write_json_atomic,
    write_npz_atomic,
)
from .io.png_check import PngError, check_rgba8

GENERATOR_NAME = "datasets_gen"
GENERATOR_VERSION = 2


def generate_dataset(
    out_dir: str = "", *, scene: Any = None, progress: bool = True, **options: Any
) -> dict[str, Any]:
    """Render a dataset into `out_dir`; return the scene profile it wrote.

    `options` are the settings by keyword, as options.SETTINGS names them (train_views=10,
    width=64, height=48, lens=35.0, pixel_aspect=(2, 1), full_sphere=True, shard="0/4", ...;
    the command line's flags, see options_from_keywords).  Give exactly one of `demo=True`,
    `builtin` (a name in builtin_scenes), `blend_path`, or `scene` (a bpy Scene already open in
    this session, e.g. the add-on's `bpy.context.scene`: rendered without opening any file, and
    every setting changed for the render is restored afterwards).  Opening `blend_path`
    replaces the current session's file; a built-in scene is added to it.  `check_only` runs the
    scene checks and returns the profile without rendering or writing anything.  Raises
    DatasetGenError for bad input, TypeError naming an unknown keyword.
    """
    if scene is not None and options.get("blend_path") is not None:
        raise DatasetGenError("give blend_path or scene (the open scene), not both")
    return run(options_from_keywords(out_dir=out_dir, open_scene=scene is not None, **options),
               progress=progress, scene=scene)


def split_poses(options: GeneratorOptions, split: str) -> list[trajectories.RigPose]:
    """The rig poses of one split: random (hemisphere or sphere) for train/val, the spiral for test."""
    count = options.views(split)
    if split == "test":
        return trajectories.test_spiral_poses(count)
    rng = trajectories.split_rng(options.seed, split)
    return trajectories.hemisphere_poses(count, rng, full_sphere=options.full_sphere)


def run(options: GeneratorOptions, progress: bool = True, scene: Any = None) -> dict[str, Any]:
    """Generate the dataset described by `options` (see generate_dataset); return the scene profile."""
    started = time.perf_counter()
    options.validate()
    out_dir = os.path.abspath(options.out_dir) if options.out_dir else ""
    if not options.check_only:
        check_output_dir(out_dir, options)

    journal = blender_journal()
    try:
        return _run_in_blender(options, out_dir, progress, scene, journal, started)
    finally:
        journal.restore()


def blender_journal() -> Any:
    """A new SettingsJournal; DatasetGenError when this Python has no Blender module.

    bpy-facing modules are imported only now, so bad input is reported without waiting for Blender."""
    try:
        from .blender.scene_state import SettingsJournal
    except ModuleNotFoundError as error:
        if error.name not in ("bpy", "bmesh", "mathutils"):
            raise
        raise DatasetGenError(
            f"this Python ({sys.executable}) has no Blender module (bpy): use the project's Python, "
            ".venv/bin/python (`make setup` creates it), or run `blender -b --python datasets_gen/generate.py -- ...`"
        ) from None
    return SettingsJournal()


@dataclass
class _Survey:
    """A loaded, checked scene: what it is, how it is framed, and its profile."""

    scene: Any
    view_layer: Any
    source: dict[str, Any]
    camera: CameraSettings
    intrinsics: Intrinsics
    outcome: CheckOutcome
    file_settings: dict[str, Any]
    frame: Similarity
    frame_record: dict[str, Any]
    profile: dict[str, Any]


def _run_in_blender(
    options: GeneratorOptions, out_dir: str, progress: bool, scene: Any, journal: Any, started: float
) -> dict[str, Any]:
    import bpy

    from .blender.render import add_dataset_camera, configure_render, render_settings_record

    survey = _survey(options, scene, journal)
    if options.check_only:
        _scene_files(survey)  # their records only: the profile returned is the one a render writes
        return survey.profile

    settings = settings_record(options, survey.camera, survey.source)
    _require_consistent_folder(out_dir, options, settings, bpy.app.version_string)
    prior, surface = _scene_files(survey)
    if "colmap" in options.formats and surface is None:  # before hours of rendering, not after
        raise DatasetGenError(f"--format colmap cannot sample points on the scene's surface: "
                              f"{survey.profile.get('geometry_reason')}")
    depth_splits = [split for split in SPLITS if options.wants_depth_normals(split) and options.views(split)]
    device = configure_render(
        survey.scene, survey.view_layer, journal, camera=survey.camera, samples=options.samples,
        seed=options.seed, device=options.device, color_management=options.color_management,
        passes=bool(depth_splits),
    )
    add_dataset_camera(survey.scene, journal, survey.camera, survey.frame)
    generator = _generator_record(options, settings, render_settings_record(survey.scene, device),
                                  survey.outcome, survey.file_settings)
    prepare_output_dir(out_dir, options, {
        "generator": GENERATOR_NAME, "settings": settings, "blender_version": bpy.app.version_string,
        "shard": [options.shard.index, options.shard.count] if options.shard else None,
    })
    _write_scene_file(out_dir, PRIOR_NAME, prior)
    _write_scene_file(out_dir, GEOMETRY_NAME, surface)
    setup_seconds = time.perf_counter() - started
    documents, timing = _render_views(options, survey, out_dir, depth_splits, generator, progress)

    if options.shard is None:
        remove_stale_frames(out_dir, {split: options.views(split) for split in SPLITS}, depth_splits)
    for split in SPLITS:
        document = documents[split]
        if options.shard is not None:
            document["shard"] = {"index": options.shard.index, "count": options.shard.count,
                                 "scene_profile": survey.profile}
        write_json_atomic(os.path.join(out_dir, transforms_name(split, options.shard)), document)
    if options.shard is None:
        write_json_atomic(os.path.join(out_dir, PROFILE_NAME), survey.profile)
        write_formats(out_dir, options.formats, documents, survey.profile, progress)
    finish_run(out_dir, options.shard)
    _report_timing(setup_seconds, *timing)
    return survey.profile


def _survey(options: GeneratorOptions, scene: Any, journal: Any) -> _Survey:
    """Load the scene, check it (refusing with DatasetGenError), fit it, and build its profile."""
    from .blender.render import read_scene_camera
    from .blender.scene_bounds import collect_geometry, render_view_layer, reveal_render_visible
    from .blender.scene_facts import describe_material, describe_world, missing_files, source_settings, texture_records

    scene, source = load_scene(options, scene)
    label = source.get("file", source["source"])
    view_layer = render_view_layer(scene)
    camera = options.camera
    if options.use_scene_camera:
        camera = read_scene_camera(scene)
        validate_camera(camera)
    intrinsics = camera.intrinsics()
    file_settings = source_settings(scene, view_layer)

    missing = missing_files()
    reveal_render_visible(scene, view_layer, journal)
    geometry = collect_geometry(scene, view_layer)
    facts = SceneFacts(
        scene=scene.name, source=label, engine=scene.render.engine,
        renderable_objects=geometry.objects, render_hidden_objects=geometry.hidden,
        other_objects=geometry.others, missing_files=missing,
        view_transform=file_settings["view_transform"], look=file_settings["look"],
        exposure=file_settings["exposure"], gamma=file_settings["gamma"],
        film_transparent=file_settings["film_transparent"],
    )
    outcome = evaluate(facts, options.allow_missing, options.color_management)
    if outcome.errors:
        raise DatasetGenError(outcome.error_message(label))
    frame, frame_record = _world_to_nerf(options, geometry, intrinsics, outcome.notes)
    for note in outcome.notes:
        print(f"{GENERATOR_NAME}: note: {note}", file=sys.stderr)

    materials = [classify_material(describe_material(name, users)).record()
                 for name, users in sorted(geometry.materials.items())]
    low, high = thickened(*frame.bounds(geometry.low, geometry.high))  # type: ignore[arg-type]
    builtin = {"builtin": options.builtin_name} if options.builtin_name is not None else {}
    profile = scene_profile(
        source["source"], low, high, **builtin,
        bounds_frame="NeRF frame: p_nerf = scale * p_blender + translation (world_to_nerf)",
        world_to_nerf=frame_record,
        bounding_sphere={"centre": list(frame.apply(geometry.centre)), "radius": geometry.radius * frame.scale},
        view_dependent=any(material["view_dependent"] for material in materials),
        transparency=any(material["transparent"] for material in materials),
        materials=materials,
        objects=geometry.objects,
        hidden_objects=sorted(geometry.hidden),
        lights=[_light_in_frame(light, frame) for light in geometry.lights],
        world=describe_world(scene),
        image_size=[intrinsics.w, intrinsics.h],
        textures=texture_records(),
        checks=outcome.record(),
    )
    return _Survey(scene, view_layer, source, camera, intrinsics, outcome, file_settings, frame, frame_record,
                   profile)


# Writes one of the scene's files to the path it is given.
FileWriter = Callable[[str], None]


def _scene_files(survey: _Survey) -> tuple[Optional[FileWriter], Optional[FileWriter]]:
    """The writers of the occupancy prior and of the true surface, from one walk of the scene's
    renderable triangles; each recorded in the profile, or why not (then None).

    Debian's Blender has no numpy: its datasets record why they have neither instead.
    """
    try:
        import numpy  # noqa: F401
    except ImportError:
        reason = "this Blender's Python has no numpy"
        return _no_occupancy_prior(survey.profile, reason), _no_scene_geometry(survey.profile, reason)
    from .blender.scene_occupancy import collect_parts

    started = time.perf_counter()
    region_of = {material["name"]: APPEARANCE_REGIONS.index(material["region"])
                 for material in survey.profile["materials"]}
    material_of = {material["name"]: index for index, material in enumerate(survey.profile["materials"])}
    scene_parts = collect_parts(survey.view_layer, survey.frame, region_of, material_of)
    return _occupancy_prior(survey, scene_parts, started), _scene_geometry(survey, scene_parts)


def _occupancy_prior(survey: _Survey, scene_parts: Any, started: float) -> Optional[FileWriter]:
    """Voxelise the scene into the profile's `occupancy_prior`; return its npz's writer (None without)."""
    from .blender.scene_occupancy import build_occupancy_prior

    try:
        record, arrays = build_occupancy_prior(scene_parts)
    except ValueError as error:
        return _no_occupancy_prior(survey.profile, f"nothing could be voxelised: {error}")
    survey.profile["occupancy_prior"] = record
    print(f"{GENERATOR_NAME}: occupancy prior: {'x'.join(map(str, record['resolution']))} cells, surface "
          f"{record['surface_fraction']:.1%}, solid {record['solid_fraction']:.1%} "
          f"({time.perf_counter() - started:.1f} s)", file=sys.stderr)
    return lambda path: write_npz_atomic(path, arrays)


def _no_occupancy_prior(profile: dict[str, Any], reason: str) -> None:
    profile["occupancy_prior"] = None
    profile["occupancy_prior_reason"] = reason
    print(f"{GENERATOR_NAME}: note: no occupancy prior: {reason}", file=sys.stderr)


def _scene_geometry(survey: _Survey, scene_parts: Any) -> Optional[FileWriter]:
    """Weld the scene's triangles into the profile's `geometry` (the truth `eval --geometry`
    measures a NeRF against); return its PLY's writer (None without)."""
    from .io.surface_mesh import geometry_record, weld, write_ply_atomic

    triangles = scene_parts.all_triangles()
    if len(triangles) == 0:
        return _no_scene_geometry(survey.profile, "no renderable object could be meshed")
    vertices, faces, materials = weld(triangles, scene_parts.all_materials())
    survey.profile["geometry"] = geometry_record(len(faces), len(vertices), scene_parts.filled_boxes,
                                                 scene_parts.margin_reasons)
    print(f"{GENERATOR_NAME}: scene geometry: {len(faces)} triangles", file=sys.stderr)
    return lambda path: write_ply_atomic(path, vertices, faces, materials)


def _no_scene_geometry(profile: dict[str, Any], reason: str) -> None:
    profile["geometry"] = None
    profile["geometry_reason"] = reason
    print(f"{GENERATOR_NAME}: note: no scene geometry file: {reason}", file=sys.stderr)


def _write_scene_file(out_dir: str, name: str, write: Optional[FileWriter]) -> None:
    """Write one of the scene's files atomically (each shard writes the same one); remove an
    earlier run's when there is none."""
    path = os.path.join(out_dir, name)
    try:
        if write is not None:
            write(path)
        elif os.path.isfile(path):
            os.remove(path)
    except OSError as error:
        raise DatasetGenError(f"cannot write {path}: {error.strerror}") from None


def _render_views(
    options: GeneratorOptions,
    survey: _Survey,
    out_dir: str,
    depth_splits: Sequence[str],
    generator: dict[str, Any],
    progress: bool,
) -> tuple[dict[str, dict], tuple[int, float, float]]:
    """Render this run's views (skipping verified ones on --resume); return the split documents
    and (views rendered, seconds in the loop, seconds inside Cycles)."""
    from .blender.render import place_camera, render_view

    frame, intrinsics = survey.frame, survey.intrinsics
    factors = ray_length_factors(intrinsics) if depth_splits else None
    plan = {split: _owned_views(options, split) for split in SPLITS}
    done = _verified_views(out_dir, plan, intrinsics, depth_splits) if options.resume else set()
    total = sum(len(indices) for indices in plan.values()) - len(done)
    if done:
        print(f"{GENERATOR_NAME}: --resume: {len(done)} views already complete, {total} to render",
              file=sys.stderr)
    cycles_seconds = 0.0
    loop_start = time.perf_counter()
    documents: dict[str, dict] = {}
    with ViewProgress(total, enabled=progress) as bar:
        for split in SPLITS:
            poses = split_poses(options, split)
            rotation = trajectories.rotation_step(len(poses))
            with_depth = split in depth_splits
            frames = []
            for index in plan[split]:
                blender_pose = frame.camera_to_blender(poses[index].matrix)
                actual = place_camera(survey.scene, survey.view_layer, blender_pose)
                frames.append(frame_entry(split, index, rotation, frame.camera_to_nerf(actual), with_depth))
                if (split, index) in done:
                    continue
                try:
                    cycles_seconds += render_view(
                        survey.scene, survey.view_layer, view_paths(out_dir, split, index),
                        (factors, frame.scale) if with_depth else None,
                    )
                except OSError as error:
                    raise DatasetGenError(f"cannot write {error.filename or out_dir}: {error.strerror}") from None
                bar.advance(split, index)
            documents[split] = transforms_document(
                intrinsics, frames, generator, survey.frame_record, LAYOUT_RECORD if with_depth else None
            )
    return documents, (total, time.perf_counter() - loop_start, cycles_seconds)


def load_scene(options: GeneratorOptions, scene: Any) -> tuple[Any, dict[str, Any]]:
    """The scene to render and a record of where it came from (file and SHA-256 when on disk)."""
    import bpy

    from .blender.scene_facts import blend_identity

    if options.builtin_name is not None:
        from .blender.builtin_scenes import build_builtin

        return build_builtin(options.builtin_name), builtin_scene(options.builtin_name).source_record()
    if options.open_scene:
        scene = scene if scene is not None else bpy.context.scene
        path = bpy.data.filepath
        if not path:
            return scene, {"source": "open scene (never saved)", "scene": scene.name, "sha256": None}
        if options.blend_path is None and bpy.data.is_dirty:  # the add-on, with unsaved edits
            return scene, {"source": path, "scene": scene.name, "file": path, "sha256": None,
                           "unsaved_changes": True}
        return scene, {"source": path, "scene": scene.name, **blend_identity(path)}
    path = os.path.abspath(str(options.blend_path))
    identity = blend_identity(path)
    try:
        bpy.ops.wm.open_mainfile(filepath=path)
    except RuntimeError as error:
        reason = str(error).strip().splitlines()[-1].removeprefix("Error: ")
        raise DatasetGenError(f"cannot open {path}: {reason}") from None
    scene = bpy.context.scene
    return scene, {"source": path, "scene": scene.name, **identity}


def _world_to_nerf(
    options: GeneratorOptions, geometry: Any, intrinsics: Intrinsics, notes: list[str]
) -> tuple[Similarity, dict[str, Any]]:
    """The frame the dataset is written in, and its JSON record (see frame_fit)."""
    try:
        target = fit_target_radius(intrinsics)
        half_angle = view_half_angle(intrinsics)
    except ValueError as error:
        raise DatasetGenError(f"camera settings: {error}") from None
    sphere = {"centre": geometry.centre, "radius": geometry.radius}
    if options.frame_mode == "blender":
        centre_distance = sum(c * c for c in geometry.centre) ** 0.5
        if centre_distance + geometry.radius > target / (1.0 - FIT_MARGIN):
            notes.append(
                f"--frame blender: the geometry (bounding sphere radius {geometry.radius:.4g} around a centre "
                f"{centre_distance:.4g} from the origin) may not fit the protocol's views; --frame fit frames it"
            )
        modelled = options.builtin_name is not None and options.frame is None  # the demo's own frame
        return IDENTITY, IDENTITY.record(DEMO_RULE if modelled else BLENDER_RULE,
                                         sphere_blender=sphere)
    try:
        similarity = fit_similarity(geometry.centre, geometry.radius, target)
    except ValueError as error:
        raise DatasetGenError(f"cannot fit the scene into the protocol's frame: {error}") from None
    return similarity, similarity.record(
        FIT_RULE, margin=FIT_MARGIN, half_angle_rad=half_angle, target_radius=target, sphere_blender=sphere,
    )


def _light_in_frame(light: dict[str, Any], frame: Similarity) -> dict[str, Any]:
    record = {key: value for key, value in light.items() if key != "location_blender"}
    record["location"] = list(frame.apply(light["location_blender"]))
    record["energy_units"] = "Blender's (W; W/m^2 for sun lights), not rescaled"
    return record


def _owned_views(options: GeneratorOptions, split: str) -> list[int]:
    """The view indices of a split this run renders (all, or this shard's)."""
    return [index for index in range(options.views(split)) if options.shard is None or options.shard.owns(index)]


def _verified_views(out_dir: str, plan: dict[str, list[int]], intrinsics: Intrinsics,
                    depth_splits: Sequence[str]) -> set[tuple[str, int]]:
    """Views whose PNG (and depth/normal EXRs when asked) exist and decode with the right size."""
    done = set()
    for split, indices in plan.items():
        for index in indices:
            paths = view_paths(out_dir, split, index)
            try:
                check_rgba8(paths["png"], intrinsics.w, intrinsics.h)
                if split in depth_splits:
                    check_file(paths["depth"], intrinsics.w, intrinsics.h, DEPTH_CHANNELS)
                    check_file(paths["normal"], intrinsics.w, intrinsics.h, NORMAL_CHANNELS)
            except (OSError, PngError, ExrError):
                continue
            done.add((split, index))
    return done


def _require_consistent_folder(out_dir: str, options: GeneratorOptions, settings: dict, version: str) -> None:
    """--resume and shards must continue the same dataset: refuse other settings, naming them."""
    if options.overwrite:
        return
    recorded = recorded_settings(out_dir, options.shard)
    if options.resume and recorded is not None:
        name, previous, previous_version = recorded
        current = settings
        if options.shard is None:
            # The layouts are written from the renders at the run's end: resuming a dataset with
            # other --format flags adds (or removes) them without rendering again.  Shards must
            # agree: the merge writes the layouts their settings name.
            previous, current = ({key: value for key, value in record.items() if key != "formats"}
                                 for record in (previous, settings))
        require_same_settings(previous, current, os.path.join(out_dir, name))
        if previous_version != version:
            raise DatasetGenError(
                f"{os.path.join(out_dir, name)} was rendered with Blender {previous_version}, this is "
                f"Blender {version}: its images would not match (use the same Blender, or --overwrite)"
            )
    if options.shard is not None:
        for name, previous in sibling_shard_settings(out_dir, options.shard):
            require_same_settings(previous, settings, os.path.join(out_dir, name))


def settings_record(options: GeneratorOptions, camera: CameraSettings, source: dict[str, Any]) -> dict[str, Any]:
    """Everything that decides the dataset's content: equal settings give the same dataset."""
    return {
        "scene": dict(source),
        "views": {split: options.views(split) for split in SPLITS},
        "train_val_trajectory": "sphere" if options.full_sphere else "hemisphere",
        "seed": options.seed,
        "samples": options.samples,
        "device": options.device,
        "camera": dict(camera.record(), source="scene camera" if options.use_scene_camera else "flags"),
        "frame": options.frame_mode,
        "depth_normals": options.depth_normals,
        "allow_missing": options.allow_missing,
        "color_management": options.color_management,
        # Only when asked for, so that datasets from before --format keep their settings.
        **({"formats": list(options.formats)} if options.formats else {}),
    }


def _generator_record(
    options: GeneratorOptions,
    settings: dict[str, Any],
    render_settings: dict[str, Any],
    outcome: Any,
    file_settings: dict[str, Any],
) -> dict[str, Any]:
    """Every setting of the run, so a dataset can be reproduced and audited."""
    record: dict[str, Any] = {
        "name": GENERATOR_NAME,
        "version": GENERATOR_VERSION,
        "scene_source": settings["scene"]["source"],
        "seed": options.seed,
        "views": {split: options.views(split) for split in SPLITS},
        "train_val_trajectory": settings["train_val_trajectory"],
        "test_trajectory": "spiral: two turns, tilt (cos(360deg*i/n)+1)/2*0.7 rad, azimuth 720deg*i/n",
        "rig": {
            "camera_offset_in_empty": list(trajectories.RIG_CAMERA_OFFSET),
            "radius": trajectories.RIG_RADIUS,
            "empty_euler": "XYZ = (tilt, 0, azimuth); Track-To -Z forward, +Y up",
            "frame": "radius and poses are in the NeRF frame; Blender cameras are mapped by world_to_nerf",
        },
        "pose_random_streams": "random.Random('datasets_gen/<seed>/<split>'), u then v per view",
        "pixel_convention": "cx, cy from the top-left corner, x right, y down; pixel centres at i + 0.5",
        "depth_normals": options.depth_normals,
        "allow_missing": options.allow_missing,
        "color_management": options.color_management,
        "scene_checks": outcome.record(),
        "source_settings": file_settings,
        "settings": settings,
    }
    record.update(render_settings)
    return record


def _report_timing(setup: float, views: int, loop: float, cycles: float) -> None:
    """One line on stderr: time per view inside Cycles and what the generator adds around it."""
    if views == 0:
        print(f"{GENERATOR_NAME}: no view to render (setup {setup:.1f} s)", file=sys.stderr)
        return
    print(
        f"{GENERATOR_NAME}: rendered {views} view{'s' if views > 1 else ''} in {loop:.1f} s: "
        f"{cycles / views:.3f} s per view inside "
        f"Cycles, {(loop - cycles) / views:.3f} s per view added by the generator; setup {setup:.1f} s",
        file=sys.stderr,
    )
