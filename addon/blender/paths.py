"""Where things are: the scene's NeRF settings, its dataset and run folders, and the backend's
Python (chosen in the preferences, or the one Set Up Backend made)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import bpy

from nerf_contract.dataset_layout import safe_name
from nerf_contract.run_layout import ANIMATIONS_DIR, ASSET_DIR

from ..core.jobs import python_in_venv
from ..core.torch_builds import PlatformFacts, TorchBuild, choose_build, detect_facts

# The add-on's own package (``bl_ext.REPO.nerf_from_blender`` installed), which Blender names its
# preferences and user folder by; this module is in its blender/.
ADDON_PACKAGE = __package__.rpartition(".")[0]


def settings(context):
    return context.scene.nerf


def dataset_dir(context) -> Path:
    return Path(bpy.path.abspath(settings(context).dataset_dir)).resolve()


def run_dir(context) -> Path:
    return Path(bpy.path.abspath(settings(context).run_dir)).resolve()


def animation_dir(context) -> Path:
    """Where the run's renders of the scene camera's animation go: ``RUN/animation/CAMERA``
    (the camera path's own folder name, so the CLI and the add-on agree)."""
    camera = context.scene.camera
    name = safe_name(camera.name if camera is not None else "camera")
    return run_dir(context) / ANIMATIONS_DIR / name


def asset_dir(context) -> Path:
    """Where Import NeRF Asset bakes the run's asset: ``RUN/asset``."""
    return run_dir(context) / ASSET_DIR


def managed_venv() -> Path:
    """Where Set Up Backend puts the backend's virtual environment (the extension's user folder)."""
    try:
        return Path(bpy.utils.extension_path_user(ADDON_PACKAGE, path="backend-venv", create=True))
    except (ValueError, AttributeError):  # not installed as an extension (a checkout)
        return Path(bpy.utils.user_resource("SCRIPTS", path="nerf_from_blender_backend", create=True))


def _preferences(context):
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    return addon.preferences if addon is not None else None


@lru_cache(maxsize=1)
def platform_facts() -> PlatformFacts:
    """This machine's platform and GPU, found once per Blender session (nvidia-smi and rocminfo
    take a moment; the panel draws many times a second)."""
    return detect_facts()


def torch_build(context) -> TorchBuild:
    """The PyTorch build Set Up Backend installs: detected, or forced in the preferences."""
    prefs = _preferences(context)
    return choose_build(platform_facts(), prefs.torch_build if prefs is not None else "auto")


def backend_python(context) -> str:
    prefs = _preferences(context)
    chosen = prefs.python_path if prefs is not None else ""
    if chosen:
        return bpy.path.abspath(chosen)
    managed = python_in_venv(managed_venv())
    return str(managed) if managed.is_file() else ""
