"""Where the add-on finds the backends. Plain Python, no bpy.

The add-on imports ``datasets_gen`` and ``nerf_contract`` like any library: the built extension
ships them as a wheel that Blender installs beside its own modules (the manifest's ``wheels``;
Blender's recommended way to bundle Python modules), and a checkout's tests find them at the
repository root. The backend runs in another Python, with ``backend_root()`` (the folder holding
``nerf_backend/`` and ``nerf_contract/``: inside the extension, or the repository root) on its
path; the generator's Blender script is the installed ``datasets_gen``'s own."""

from __future__ import annotations

import json
from pathlib import Path

import datasets_gen

ADDON_DIR = Path(__file__).resolve().parents[1]  # the add-on's folder (this module is in its core/)


def is_bundled() -> bool:
    """Whether this is the built extension (the backend's sources inside it) or a checkout."""
    return (ADDON_DIR / "nerf_backend").is_dir()


def backend_root() -> Path:
    """The folder holding ``nerf_backend/`` and ``nerf_contract/``: the backend's PYTHONPATH."""
    return ADDON_DIR if is_bundled() else ADDON_DIR.parent


def generator_script() -> Path:
    """The generator's entry point for a background Blender (``blender -b --python SCRIPT``)."""
    return Path(datasets_gen.__file__).resolve().parent / "generate.py"


def backend_requirements() -> Path:
    return backend_root() / "nerf_backend" / "requirements.txt"


def backend_presets() -> list[tuple[str, str, str]]:
    """The backend's training presets as ``(name, label, description)``, in its order, read
    from the file the backend builds them from (the add-on never imports torch)."""
    path = backend_root() / "nerf_backend" / "configs" / "presets.json"
    entries = json.loads(path.read_text(encoding="utf-8"))
    return [(name, entry["label"], entry["description"]) for name, entry in entries.items()]
