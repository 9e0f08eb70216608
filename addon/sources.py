"""Where the add-on finds ``datasets_gen`` and ``nerf_backend``: inside itself in the built
extension (``make extension`` copies both in), or beside it in a checkout of the repository.
Plain Python, no bpy."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

ADDON_DIR = Path(__file__).resolve().parent


def is_bundled() -> bool:
    return (ADDON_DIR / "datasets_gen").is_dir() and (ADDON_DIR / "nerf_backend").is_dir()


def source_root() -> Path:
    """The folder holding ``nerf_backend/`` and ``datasets_gen/``: the backend's PYTHONPATH."""
    return ADDON_DIR if is_bundled() else ADDON_DIR.parent


def datasets_gen(module: str = ""):
    """Import ``datasets_gen`` (or one of its modules) from wherever it lives."""
    suffix = f".{module}" if module else ""
    if is_bundled():
        return importlib.import_module(f"{__package__}.datasets_gen{suffix}")
    root = str(source_root())
    if root not in sys.path:  # a checkout: the repository root holds the package
        sys.path.insert(0, root)
    return importlib.import_module(f"datasets_gen{suffix}")


def backend_requirements() -> Path:
    return source_root() / "nerf_backend" / "requirements.txt"


def backend_presets() -> list[tuple[str, str, str]]:
    """The backend's training presets as ``(name, label, description)``, in its order, read
    from the file the backend builds them from (the add-on never imports torch)."""
    path = source_root() / "nerf_backend" / "configs" / "presets.json"
    entries = json.loads(path.read_text(encoding="utf-8"))
    return [(name, entry["label"], entry["description"]) for name, entry in entries.items()]
