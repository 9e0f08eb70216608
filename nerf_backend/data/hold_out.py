"""A dataset whose views are all in one split (nerf_synthetic's public training views, a capture
with only ``transforms_train.json``) split into train / val / test by holding out every N-th
view, as the LLFF and Mip-NeRF 360 protocols do: views ``0, N, 2N, ...`` are the test split;
the first ``val_views`` views half-way between two test views (``N/2, N + N/2, ...``) are the
validation split; every other view trains. The images are linked (copied where the filesystem
cannot link) into the new dataset's own folders, so the source is never touched.

Example:
    >>> split = hold_out_indices(20, every=8, val_views=2)
    >>> split["test"], split["val"], len(split["train"])
    ([0, 8, 16], [4, 12], 15)
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from nerf_contract.dataset_layout import SPLITS, transforms_name, view_names

from ..core.errors import DatasetError
from ..core.files import write_json


def hold_out_indices(views: int, every: int, val_views: int) -> dict[str, list[int]]:
    """Which of ``views`` views go to each split (see the module's notes)."""
    if every < 2:
        raise ValueError(f"holding out every {every}th view leaves nothing to train on; use 2 or more")
    test = list(range(0, views, every))
    val = [index for index in range(every // 2, views, every) if index % every != 0][:val_views]
    held = set(test) | set(val)
    return {"train": [index for index in range(views) if index not in held], "val": val, "test": test}


def write_held_out_dataset(source: Path, out: Path, every: int = 8, val_views: int = 2,
                           split: str = "train") -> dict[str, int]:
    """Write ``out`` (a new folder) from ``source/transforms_{split}.json`` and its images; returns
    the number of views in each split. Refuses an existing ``out`` and a source that is not a
    dataset, before writing anything."""
    transforms_path = source / transforms_name(split)
    try:
        document = json.loads(transforms_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DatasetError(f"{transforms_path}: not found (is {source} a dataset folder?)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{transforms_path}: cannot be read as JSON ({exc})") from None
    frames = document.get("frames") if isinstance(document, dict) else None
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{transforms_path}: has no 'frames' list to split")
    images = [_frame_image(source, frame, transforms_path, number) for number, frame in enumerate(frames)]
    if out.exists():
        raise DatasetError(f"{out}: already exists; choose a new folder for the split dataset")
    indices = hold_out_indices(len(frames), every, val_views)
    header = {key: value for key, value in document.items() if key != "frames"}
    out.mkdir(parents=True)
    for name in SPLITS:
        (out / name).mkdir()
        written = []
        for number, index in enumerate(indices[name]):
            target = out / name / view_names(number)["png"]
            _link_or_copy(images[index], target)
            written.append({**frames[index], "file_path": f"./{name}/{target.stem}",
                            "source_file_path": frames[index]["file_path"]})
        write_json(out / transforms_name(name), {**header, "frames": written})
    return {name: len(indices[name]) for name in SPLITS}


def _frame_image(source: Path, frame: object, transforms_path: Path, number: int) -> Path:
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
        raise DatasetError(f"{transforms_path}: frame {number} has no 'file_path'")
    relative = frame["file_path"]
    image = source / (relative if relative.lower().endswith(".png") else relative + ".png")
    if not image.is_file():
        raise DatasetError(f"{transforms_path}: frame {number}'s image {image} not found")
    return image


def _link_or_copy(source: Path, target: Path) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)
