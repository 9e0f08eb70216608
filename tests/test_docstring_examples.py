"""The examples in the backend's docstrings run and print what they say (nerfacc's habit:
each function of the functional API documented with an example that works)."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import addon.core
import datasets_gen.core
import datasets_gen.io
import nerf_backend
import nerf_contract


def _modules(package) -> list[str]:
    return sorted(info.name for info in pkgutil.walk_packages(package.__path__, package.__name__ + ".")
                  if not info.name.endswith("__main__"))


# The backend, datasets_gen's and the add-on's plain sides (their Blender sides import bpy), and
# the contract.
MODULES = (_modules(nerf_backend) + _modules(datasets_gen.core) + _modules(datasets_gen.io) + _modules(addon.core)
           + _modules(nerf_contract))


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0


def test_the_functional_api_has_examples():
    for name in ("nerf_backend.model_components.marcher", "nerf_backend.model_components.volume_rendering",
                 "nerf_backend.metrics.registry", "nerf_backend.field_components.hash_encoding"):
        assert doctest.DocTestFinder().find(importlib.import_module(name)), name
