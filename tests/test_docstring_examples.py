"""The examples in the backend's docstrings run and print what they say (nerfacc's habit:
each function of the functional API documented with an example that works)."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import nerf_backend

MODULES = sorted(info.name for info in pkgutil.walk_packages(nerf_backend.__path__, "nerf_backend.")
                 if not info.name.endswith("__main__"))
# datasets_gen's pure modules with examples (its others import bpy).
MODULES += ["datasets_gen.camera_path", "datasets_gen.formats", "datasets_gen.png_image", "datasets_gen.zbuffer",
            "datasets_gen.colmap_model", "datasets_gen.surface_mesh"]
# The add-on's plain modules with examples (no bpy).
MODULES += ["addon.torch_builds", "addon.backend_setup"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0


def test_the_functional_api_has_examples():
    for name in ("nerf_backend.model_components.marcher", "nerf_backend.model_components.volume_rendering",
                 "nerf_backend.metrics.registry", "nerf_backend.field_components.hash_encoding"):
        assert doctest.DocTestFinder().find(importlib.import_module(name)), name
