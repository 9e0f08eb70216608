"""Reading back a split's JSON that datasets_gen wrote (``transforms_{split}.json``): what a
camera path and an asset's renders need of a dataset (its ``world_to_nerf``, its cameras, its
generator settings)."""

from __future__ import annotations

import json
import os
from typing import Any, Sequence

from nerf_contract.dataset_layout import transforms_name

from ..core.options import DatasetGenError


def read_split_document(dataset_dir: str, split: str, needs: Sequence[str], missing_hint: str) -> dict[str, Any]:
    """``transforms_{split}.json`` of ``dataset_dir``, holding the keys ``needs``; DatasetGenError
    naming the file otherwise (``missing_hint``: what to do when the file is not there)."""
    path = os.path.join(dataset_dir, transforms_name(split))
    try:
        with open(path, encoding="utf-8") as handle:
            document = json.load(handle)
    except FileNotFoundError:
        raise DatasetGenError(f"{path}: not found; {missing_hint}") from None
    except (OSError, ValueError) as error:
        raise DatasetGenError(f"{path}: cannot read the dataset's JSON ({error})") from None
    missing = [key for key in needs if not isinstance(document, dict) or not document.get(key)]
    if missing:
        raise DatasetGenError(f"{path}: has no {missing[0]!r}; was the dataset written by datasets_gen?")
    return document
