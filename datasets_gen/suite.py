"""`python -m datasets_gen --suite DIR`: the benchmark suite's datasets, one folder a scene.

DIR/NAME for every built-in trap scene and the demo (NAME = the builtin's name) and for each
`--suite-scene SCENE.blend` (NAME = the file's stem), all with the same flags (views,
resolution, samples, --allow-missing...).  Run again, the suite picks up where it stopped:

* a complete dataset (its transforms_*.json written) is kept untouched, once its recorded
  settings are this call's (a dataset made with other flags, or from a .blend that has changed
  since, is refused before anything renders: pass --overwrite to render it again);
* an incomplete one (an interrupted render) is resumed (the generator's --resume);
* a missing one is rendered.

Every scene renders in this process, one after the other, from an empty Blender session (a
.blend opens in its place); a scene that fails is reported and the others still render.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from dataclasses import dataclass
from typing import Any, Optional, Sequence

from nerf_contract.dataset_layout import SPLITS

from .core.builtin_scenes import SUITE_BUILTINS, builtin_scene
from .core.options import DEFAULT_OPTIONS, DatasetGenError, GeneratorOptions
from .io.output_dir import read_json, require_same_settings, transforms_name

PROG = "datasets_gen --suite"


@dataclass(frozen=True)
class SuiteScene:
    """One dataset of the suite: its name, and the options that render it into DIR/NAME."""

    name: str
    options: GeneratorOptions

    @property
    def out_dir(self) -> str:
        return self.options.out_dir


def plan_suite(template: GeneratorOptions, suite_dir: str, blend_paths: Sequence[str]) -> list[SuiteScene]:
    """The suite's scenes, each with `template`'s flags; DatasetGenError for a bad .blend or
    two scenes of the same name (before anything is rendered)."""
    if os.path.exists(suite_dir) and not os.path.isdir(suite_dir):
        raise DatasetGenError(f"--suite: {suite_dir} exists and is not a folder")
    # The template's scene source and its one-dataset settings, back to the defaults.
    common = {name: getattr(DEFAULT_OPTIONS, name) for name in (
        "demo", "demo_variant", "builtin", "blend_path", "open_scene", "resume", "shard", "check_only")}
    plan = [SuiteScene(name, dataclasses.replace(template, **{**common, "builtin": name,
                                                              "out_dir": os.path.join(suite_dir, name)}))
            for name in SUITE_BUILTINS]
    for path in blend_paths:
        name = os.path.splitext(os.path.basename(path))[0]
        clash = next((scene for scene in plan if scene.name == name), None)
        if clash is not None:
            what = "a built-in scene" if clash.options.builtin else clash.options.blend_path
            raise DatasetGenError(f"--suite-scene {path}: its name {name!r} is taken by {what}; rename the file")
        options = dataclasses.replace(template, **{**common, "blend_path": path,
                                                   "out_dir": os.path.join(suite_dir, name)})
        plan.append(SuiteScene(name, options.validate()))
    return plan


def is_complete(out_dir: str) -> bool:
    """True when the folder holds a finished dataset (its JSON files are written last)."""
    return all(os.path.isfile(os.path.join(out_dir, transforms_name(split))) for split in SPLITS)


def _recorded_settings(out_dir: str) -> Optional[dict[str, Any]]:
    generator = (read_json(os.path.join(out_dir, transforms_name("train"))) or {}).get("generator", {})
    settings = generator.get("settings") if isinstance(generator, dict) else None
    return settings if isinstance(settings, dict) else None


def check_kept_dataset(scene: SuiteScene) -> None:
    """Refuse (DatasetGenError naming the differences) a complete dataset that this call's flags
    would not make: other settings, another built-in scene, or a .blend whose content changed."""
    from .blender.scene_facts import blend_identity
    from .generator import settings_record

    where = os.path.join(scene.out_dir, transforms_name("train"))
    recorded = _recorded_settings(scene.out_dir)
    if recorded is None:
        raise DatasetGenError(f"{where}: no generator settings recorded; pass --overwrite to render it again")
    options = scene.options
    if options.builtin is not None:
        source = builtin_scene(options.builtin).source_record()
    else:  # the scene's name inside the file is only known once it is open: compare the file's content
        identity = blend_identity(str(options.blend_path))
        previous = recorded.get("scene", {}) if isinstance(recorded.get("scene"), dict) else {}
        if previous.get("sha256") != identity["sha256"]:
            raise DatasetGenError(f"{where} was rendered from another version of {options.blend_path} "
                                  "(its SHA-256 differs); pass --overwrite to render it again")
        source = previous
    expected = settings_record(options, options.camera, source)
    if options.use_scene_camera:  # read from the .blend when it renders: not known here
        expected["camera"] = recorded.get("camera")
    require_same_settings(recorded, expected, where)


def _reset_blender_session() -> None:
    """An empty session, so that no scene sees another's data (names, images, settings)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)


def run_suite(plan: Sequence[SuiteScene], progress: bool = True) -> int:
    """Render the suite; return the exit status (2 when a scene failed, after all were tried)."""
    try:
        import bpy  # noqa: F401  (every scene renders in this process)
    except ModuleNotFoundError:
        raise DatasetGenError(f"--suite needs Blender's Python module (bpy), which this Python ({sys.executable}) "
                              "lacks: use the project's Python, .venv/bin/python (`make setup` creates it), or run "
                              "it in Blender: blender -b --python datasets_gen/generate.py -- --suite DIR ...") from None
    from .generator import run

    overwrite = bool(plan) and plan[0].options.overwrite
    if not overwrite:  # refuse kept datasets that other flags made, before anything renders
        for scene in plan:
            if is_complete(scene.out_dir):
                check_kept_dataset(scene)
    outcomes: list[tuple[str, str]] = []
    for number, scene in enumerate(plan, 1):
        label = f"{PROG}: [{number}/{len(plan)}] {scene.name}"
        if not overwrite and is_complete(scene.out_dir):
            print(f"{label}: complete, kept ({scene.out_dir})", file=sys.stderr, flush=True)
            outcomes.append((scene.name, "kept"))
            continue
        resume = not overwrite and os.path.isdir(scene.out_dir) and bool(os.listdir(scene.out_dir))
        action = "resuming the incomplete dataset in" if resume else "rendering into"
        print(f"{label}: {action} {scene.out_dir}", file=sys.stderr, flush=True)
        started = time.perf_counter()
        try:
            _reset_blender_session()
            run(dataclasses.replace(scene.options, resume=resume), progress=progress)
        except (DatasetGenError, OSError) as error:
            message = str(error) if isinstance(error, DatasetGenError) else f"{error.filename or ''}: {error.strerror}"
            print(f"{label}: error: {message}", file=sys.stderr, flush=True)
            outcomes.append((scene.name, f"failed: {message}"))
            continue
        outcomes.append((scene.name, f"{'resumed' if resume else 'rendered'} in {time.perf_counter() - started:.1f} s"))
    width = max(len(name) for name, _ in outcomes) if outcomes else 0
    print(f"{PROG}: done", file=sys.stderr)
    for name, outcome in outcomes:
        print(f"  {name:<{width}}  {outcome}", file=sys.stderr)
    failed = [name for name, outcome in outcomes if outcome.startswith("failed")]
    if failed:
        print(f"{PROG}: {len(failed)} of {len(plan)} scenes failed ({', '.join(failed)}); "
              "fix them and run the same command again (the others are kept)", file=sys.stderr)
        return 2
    return 0
