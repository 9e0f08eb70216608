"""Join the shards of a dataset rendered by several machines (`--shard K/N`, then `--merge`).

Each shard renders the views whose index % N == K in every split and writes
`transforms_{split}.shard-K-of-N.json` (its frames, the shared generator record and, under
"shard", its index and the scene profile).  `merge` checks that all N shards are there with the
same settings, that every view appears exactly once and its files exist, then writes the
final transforms_{split}.json and scene_profile.json (atomically, last) and removes the shard
JSON files: the folder then equals the one an unsharded run writes.  The occupancy prior
(occupancy_prior.npz) and the scene geometry (scene_geometry.ply) are the same for every shard,
which each wrote atomically: the merge only checks that they are there when the profile names them.

No bpy: a merge can run on any machine that sees the folder.
"""

from __future__ import annotations

import os
from typing import Any

from nerf_contract.dataset_layout import GEOMETRY_NAME, PRIOR_NAME, PROFILE_NAME, SPLITS

from ..core.options import DatasetGenError, Shard
from .dataset_json import frame_index
from .formats import write_formats
from .output_dir import (
    read_json,
    remove_stale_frames,
    settings_difference,
    shard_json_files,
    transforms_name,
    write_json_atomic,
)


def merge(out_dir: str) -> dict[str, Any]:
    """Merge the shard JSON files in `out_dir` into the dataset's JSON; return the scene profile."""
    out_dir = os.path.abspath(out_dir)
    if not os.path.isdir(out_dir):
        raise DatasetGenError(f"--merge: folder not found: {out_dir}")
    files = shard_json_files(out_dir)
    if not files:
        raise DatasetGenError(f"--merge: {out_dir} holds no transforms_*.shard-K-of-N.json files")
    counts = sorted({shard.count for _, shard, _ in files})
    if len(counts) != 1:
        raise DatasetGenError(f"--merge: {out_dir} mixes shards of {' and '.join(map(str, counts))}")
    count = counts[0]

    documents: dict[str, list[dict]] = {}
    for split in SPLITS:
        documents[split] = []
        for index in range(count):
            shard = Shard(index, count)
            name = transforms_name(split, shard)
            document = read_json(os.path.join(out_dir, name))
            if document is None:
                raise DatasetGenError(
                    f"--merge: {name} is missing or unreadable in {out_dir}: shard {index}/{count} "
                    "has not finished (run it, with --resume if it was interrupted)"
                )
            documents[split].append(document)

    reference = documents["train"][0]
    for split in SPLITS:
        for index, document in enumerate(documents[split]):
            _require_same(reference, document, f"{transforms_name(split, Shard(index, count))}")

    profile = reference["shard"]["scene_profile"]
    for key, name, what in (("occupancy_prior", PRIOR_NAME, "occupancy prior"),
                            ("geometry", GEOMETRY_NAME, "scene geometry")):
        path = os.path.join(out_dir, name)
        if isinstance(profile.get(key), dict) and not os.path.isfile(path):
            raise DatasetGenError(f"--merge: {path} is missing (every shard writes the {what}: "
                                  "run one of them again with --resume)")
    merged = {split: _merged_document(out_dir, split, documents[split]) for split in SPLITS}
    for split in SPLITS:
        write_json_atomic(os.path.join(out_dir, f"transforms_{split}.json"), merged[split])
    write_json_atomic(os.path.join(out_dir, PROFILE_NAME), profile)
    write_formats(out_dir, reference["generator"].get("settings", {}).get("formats", []), merged, profile)
    for split in SPLITS:
        for index in range(count):
            path = os.path.join(out_dir, transforms_name(split, Shard(index, count)))
            if os.path.isfile(path):
                os.remove(path)
    views = reference["generator"]["views"]
    remove_stale_frames(out_dir, views, [split for split in SPLITS if "depth_normals" in merged[split]])
    return profile


def _require_same(reference: dict, document: dict, name: str) -> None:
    """Shards must agree on everything but their frames and their own index."""
    for key in ("generator", "world_to_nerf", "camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h"):
        if reference.get(key) != document.get(key):
            differing = settings_difference(reference.get(key), document.get(key), f"{key}.")
            raise DatasetGenError(
                f"--merge: {name} was rendered with different settings ({', '.join(differing[:4])})"
            )
    if reference.get("shard", {}).get("scene_profile") != document.get("shard", {}).get("scene_profile"):
        raise DatasetGenError(f"--merge: {name} has a different scene profile (a different scene?)")


def _merged_document(out_dir: str, split: str, documents: list[dict]) -> dict:
    expected = documents[0]["generator"]["views"][split]
    frames: dict[int, dict] = {}
    for document in documents:
        shard = Shard(document["shard"]["index"], document["shard"]["count"])
        for frame in document["frames"]:
            index = frame_index(frame["file_path"])
            if not shard.owns(index) or index in frames or index >= expected:
                raise DatasetGenError(
                    f"--merge: {transforms_name(split, shard)} lists view {frame['file_path']} that is not its own"
                )
            for key in ("file_path", "depth_file_path", "normal_file_path"):
                if key in frame:
                    path = os.path.join(out_dir, frame[key] + (".png" if key == "file_path" else ""))
                    if not os.path.isfile(path):
                        raise DatasetGenError(f"--merge: {path} is missing")
            frames[index] = frame
    missing = sorted(set(range(expected)) - set(frames))
    if missing:
        raise DatasetGenError(f"--merge: {split} views {missing[:8]} are in no shard")
    document = {key: value for key, value in documents[0].items() if key not in ("shard", "frames", "generator")}
    document["frames"] = [frames[index] for index in range(expected)]
    document["generator"] = documents[0]["generator"]
    return document
