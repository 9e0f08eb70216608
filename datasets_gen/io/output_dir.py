"""The dataset folder on disk: refuse to clobber it, never leave it half-written, resume it.

A reader treats a folder as a dataset once transforms_*.json exist, so those are removed first
when overwriting or resuming and written last (each atomically); images are written under a
temporary name in the same folder and moved into place with os.replace, which is atomic on
one filesystem.

While a run is under way the folder holds a small progress file recording the run's settings
(`.datasets_gen_progress.json`, or `.datasets_gen_progress.shard-K-of-N.json` for a shard), so
that --resume can refuse a different configuration instead of mixing two datasets; it is
removed once the run's JSON is written.  A shard writes `transforms_{split}.shard-K-of-N.json`
instead of the final JSON; `shards.merge` joins them.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any, BinaryIO, Callable, Iterable, Optional

from nerf_contract import dataset_layout
from nerf_contract.dataset_layout import PROFILE_NAME, SPLITS

from ..core.options import DatasetGenError, GeneratorOptions, Shard

DATASET_JSON_NAMES = tuple(dataset_layout.transforms_name(split) for split in SPLITS) + (PROFILE_NAME,)
PROGRESS_PREFIX = ".datasets_gen_progress"
_VIEW_FILE = re.compile(r"r_(\d+)(\.png|_depth\.exr|_normal\.exr)")
_TEMPORARY = re.compile(r"\.r_(\d+)[._].*\.\d+\.tmp")
_SHARD_JSON = re.compile(r"transforms_(train|val|test)\.shard-(\d+)-of-(\d+)\.json")
_SHARD_PROGRESS = re.compile(re.escape(PROGRESS_PREFIX) + r"\.shard-(\d+)-of-(\d+)\.json")


def progress_name(shard: Optional[Shard]) -> str:
    """File name of a run's progress file."""
    return f"{PROGRESS_PREFIX}.{shard.label}.json" if shard else f"{PROGRESS_PREFIX}.json"


def transforms_name(split: str, shard: Optional[Shard] = None) -> str:
    """transforms_{split}.json, or transforms_{split}.shard-K-of-N.json for a shard."""
    return f"transforms_{split}.{shard.label}.json" if shard else dataset_layout.transforms_name(split)


def view_paths(out_dir: str, split: str, index: int) -> dict[str, str]:
    """Absolute paths of a view's files: "png", "depth", "normal"."""
    folder = os.path.join(out_dir, split)
    return {kind: os.path.join(folder, name) for kind, name in dataset_layout.view_names(index).items()}


def read_json(path: str) -> Optional[dict]:
    """The JSON object in `path`, or None when the file is missing or not a JSON object."""
    try:
        with open(path, encoding="utf-8") as handle:
            document = json.load(handle)
    except (OSError, ValueError):
        return None
    return document if isinstance(document, dict) else None


def shard_json_files(out_dir: str) -> list[tuple[str, Shard, str]]:
    """(split, shard, file name) of every shard JSON in the folder."""
    found = []
    for name in sorted(os.listdir(out_dir)) if os.path.isdir(out_dir) else ():
        match = _SHARD_JSON.fullmatch(name)
        if match:
            found.append((match.group(1), Shard(int(match.group(2)), int(match.group(3))), name))
    return found


def check_output_dir(out_dir: str, options: GeneratorOptions) -> None:
    """Refuse (DatasetGenError naming the folder) what the run must not touch; no bpy needed.

    * a path that is not a folder;
    * without --overwrite / --resume: a non-empty folder, except that a shard may share the
      folder with the other shards of its dataset (but not with its own earlier run);
    * --resume on a folder holding no run of datasets_gen.
    """
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise DatasetGenError(f"output path exists and is not a folder: {out_dir}")
    if options.overwrite or not os.path.isdir(out_dir) or not os.listdir(out_dir):
        return
    shard = options.shard
    own_progress = os.path.isfile(os.path.join(out_dir, progress_name(shard)))
    own_result = all(os.path.isfile(os.path.join(out_dir, transforms_name(split, shard))) for split in SPLITS)
    if options.resume:
        if not (own_progress or own_result):
            what = f"{progress_name(shard)} or {transforms_name('train', shard)}"
            raise DatasetGenError(f"--resume: {out_dir} holds no run of datasets_gen to resume (no {what})")
        return
    if shard is None:
        raise DatasetGenError(
            f"output folder is not empty: {out_dir} (pass --overwrite to replace its dataset "
            "or --resume to complete it)"
        )
    if own_progress:
        raise DatasetGenError(f"shard {shard.index}/{shard.count} was already started in {out_dir}: pass --resume")
    if own_result:
        raise DatasetGenError(
            f"shard {shard.index}/{shard.count} is already complete in {out_dir} "
            "(pass --resume to verify it or --overwrite to render it again)"
        )
    if any(os.path.isfile(os.path.join(out_dir, name)) for name in DATASET_JSON_NAMES[:3]):
        raise DatasetGenError(f"{out_dir} holds a complete dataset (pass --overwrite to replace it)")


def recorded_settings(out_dir: str, shard: Optional[Shard]) -> Optional[tuple[str, dict, Any]]:
    """(file name, settings, Blender version) of the run this folder holds for `shard`, if any.

    The progress file of an unfinished run wins; otherwise a finished run's JSON.
    """
    progress = read_json(os.path.join(out_dir, progress_name(shard)))
    if progress is not None and isinstance(progress.get("settings"), dict):
        return progress_name(shard), progress["settings"], progress.get("blender_version")
    name = transforms_name("train", shard)
    generator = (read_json(os.path.join(out_dir, name)) or {}).get("generator", {})
    if isinstance(generator.get("settings"), dict):
        return name, generator["settings"], generator.get("blender_version")
    return None


def sibling_shard_settings(out_dir: str, shard: Shard) -> list[tuple[str, dict]]:
    """(file name, settings) of the other shards' runs in the folder (progress files and shard JSONs)."""
    found = []
    for name in sorted(os.listdir(out_dir)) if os.path.isdir(out_dir) else ():
        progress = _SHARD_PROGRESS.fullmatch(name)
        result = _SHARD_JSON.fullmatch(name)
        match = progress or result
        if not match or (result and result.group(1) != "train"):
            continue
        other = Shard(int(match.group(2 if result else 1)), int(match.group(3 if result else 2)))
        if other == shard:
            continue
        document = read_json(os.path.join(out_dir, name)) or {}
        settings = document.get("settings") if progress else document.get("generator", {}).get("settings")
        if other.count != shard.count:
            raise DatasetGenError(
                f"{out_dir} holds shards of {other.count} ({name}); this run is a shard of {shard.count}"
            )
        if isinstance(settings, dict):
            found.append((name, settings))
    return found


def settings_difference(recorded: Any, current: Any, prefix: str = "") -> list[str]:
    """Dotted names of the settings that differ between two records (for clear refusals)."""
    if isinstance(recorded, dict) and isinstance(current, dict):
        names = []
        for key in sorted(set(recorded) | set(current), key=str):
            names += settings_difference(recorded.get(key), current.get(key), f"{prefix}{key}.")
        return names
    return [] if recorded == current else [prefix.rstrip(".")]


def require_same_settings(recorded: dict, current: dict, where: str) -> None:
    """Raise DatasetGenError naming the differing settings (with both values) if any differ."""
    differing = settings_difference(recorded, current)
    if differing:
        details = ", ".join(
            f"{name} {_lookup(recorded, name)!r} there vs {_lookup(current, name)!r} now" for name in differing[:4]
        )
        more = f" and {len(differing) - 4} more" if len(differing) > 4 else ""
        raise DatasetGenError(
            f"{where} was made with different settings ({details}{more}); rerun with the same flags, "
            "or pass --overwrite to start again"
        )


def _lookup(document: Any, dotted: str) -> Any:
    for key in dotted.split("."):
        if not isinstance(document, dict):
            return None
        document = document.get(key)
    return document


def prepare_output_dir(out_dir: str, options: GeneratorOptions, progress: dict) -> None:
    """Create the folder and split folders; remove what a new or resumed run replaces; write progress.

    The previous dataset's JSON files go first (overwrite and resume alike), so that an
    interrupted run can never be mistaken for a complete dataset; other files are left alone.
    """
    shard = options.shard
    names = [transforms_name(split, shard) for split in SPLITS]
    if shard is None or options.overwrite:
        names += list(DATASET_JSON_NAMES)
    try:
        os.makedirs(out_dir, exist_ok=True)
        for name in names:
            path = os.path.join(out_dir, name)
            if os.path.isfile(path):
                os.remove(path)
        for split in SPLITS:
            os.makedirs(os.path.join(out_dir, split), exist_ok=True)
        remove_temporary_files(out_dir, shard)
        write_json_atomic(os.path.join(out_dir, progress_name(shard)), progress)
    except OSError as error:
        raise DatasetGenError(f"cannot write to output folder {out_dir}: {error.strerror}") from None


def finish_run(out_dir: str, shard: Optional[Shard]) -> None:
    """Remove the progress file once the run's JSON is in place."""
    path = os.path.join(out_dir, progress_name(shard))
    if os.path.isfile(path):
        os.remove(path)


def temporary_path(final_path: str) -> str:
    """A sibling name for writing `final_path` before moving it into place (same filesystem)."""
    folder, name = os.path.split(final_path)
    return os.path.join(folder, f".{name}.{os.getpid()}.tmp")


def remove_temporary_files(out_dir: str, shard: Optional[Shard]) -> None:
    """Delete temporary files an interrupted run left for this run's views (not other shards')."""
    for split in SPLITS:
        folder = os.path.join(out_dir, split)
        if not os.path.isdir(folder):
            continue
        for name in os.listdir(folder):
            match = _TEMPORARY.fullmatch(name)
            if match and (shard is None or shard.owns(int(match.group(1)))):
                os.remove(os.path.join(folder, name))


def write_file_atomic(path: str, write: Callable[[BinaryIO], None]) -> None:
    """`write(handle)` into a temporary sibling, flush it to disk, then os.replace it into `path`."""
    temporary = temporary_path(path)
    try:
        with open(temporary, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.remove(temporary)


def write_json_atomic(path: str, document: Any) -> None:
    """JSON (indented, with a final newline), written atomically."""
    text = json.dumps(document, indent=2) + "\n"
    write_file_atomic(path, lambda handle: handle.write(text.encode("utf-8")))


def write_npz_atomic(path: str, arrays: dict[str, Any]) -> None:
    """numpy.savez_compressed, written atomically.

    numpy is imported here, not at the top: Blender builds without numpy never call this.
    """
    import numpy

    # A handle, not a name: given a name, savez appends ".npz".
    write_file_atomic(path, lambda handle: numpy.savez_compressed(handle, **arrays))


def remove_stale_frames(out_dir: str, frame_counts: dict[str, int], depth_splits: Iterable[str]) -> None:
    """Delete view files an earlier, different run left, so the folder matches the JSON.

    Removes r_<i>.png / r_<i>_depth.exr / r_<i>_normal.exr with i >= the split's count, and
    depth/normal files of splits that have none in this dataset.
    """
    with_depth = set(depth_splits)
    for split, count in frame_counts.items():
        folder = os.path.join(out_dir, split)
        if not os.path.isdir(folder):
            continue
        for name in os.listdir(folder):
            match = _VIEW_FILE.fullmatch(name)
            if not match:
                continue
            stale = int(match.group(1)) >= count or (match.group(2) != ".png" and split not in with_depth)
            if stale:
                os.remove(os.path.join(folder, name))
