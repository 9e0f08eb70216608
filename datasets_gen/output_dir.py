"""The dataset folder on disk: refuse to clobber it, and never leave it half-written.

A reader treats a folder as a dataset once transforms_*.json exist, so those are removed first
when overwriting and written last (each atomically); images are written under a temporary name
in the same folder and moved into place with os.replace, which is atomic on one filesystem.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any, Iterable

from .options import DatasetGenError

DATASET_JSON_NAMES = (
    "transforms_train.json",
    "transforms_val.json",
    "transforms_test.json",
    "scene_profile.json",
)
_FRAME_IMAGE = re.compile(r"r_(\d+)\.png")


def check_output_dir(out_dir: str, overwrite: bool) -> None:
    """Refuse (DatasetGenError naming the folder) a non-folder or, unless `overwrite`, a non-empty folder."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise DatasetGenError(f"output path exists and is not a folder: {out_dir}")
    if not overwrite and os.path.isdir(out_dir) and os.listdir(out_dir):
        raise DatasetGenError(
            f"output folder is not empty: {out_dir} (pass --overwrite to replace its dataset)"
        )


def prepare_output_dir(out_dir: str, splits: Iterable[str], overwrite: bool) -> None:
    """Create `out_dir` and its split folders, refusing a non-empty folder unless `overwrite`.

    With `overwrite`, the previous dataset's JSON files are removed up front so that an
    interrupted run can never be mistaken for a complete dataset; other files are left alone.
    """
    check_output_dir(out_dir, overwrite)
    if os.path.isdir(out_dir):
        for name in DATASET_JSON_NAMES:
            path = os.path.join(out_dir, name)
            if os.path.isfile(path):
                os.remove(path)
    try:
        for split in splits:
            os.makedirs(os.path.join(out_dir, split), exist_ok=True)
    except OSError as error:
        raise DatasetGenError(f"cannot create output folder {out_dir}: {error.strerror}") from None


def temporary_path(final_path: str) -> str:
    """A sibling name for writing `final_path` before moving it into place (same filesystem)."""
    folder, name = os.path.split(final_path)
    return os.path.join(folder, f".{name}.{os.getpid()}.tmp")


def write_json_atomic(path: str, document: Any) -> None:
    """Write JSON to a temporary sibling, flush it to disk, then os.replace it into `path`."""
    temporary = temporary_path(path)
    try:
        with open(temporary, "w", encoding="utf-8") as handle:
            json.dump(document, handle, indent=2)
            handle.write("\n")
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.remove(temporary)


def remove_stale_frames(split_dir: str, frame_count: int) -> None:
    """Delete r_<i>.png left by an earlier, longer run (i >= frame_count) so the folder matches the JSON."""
    if not os.path.isdir(split_dir):
        return
    for name in os.listdir(split_dir):
        match = _FRAME_IMAGE.fullmatch(name)
        if match and int(match.group(1)) >= frame_count:
            os.remove(os.path.join(split_dir, name))
