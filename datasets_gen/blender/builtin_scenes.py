"""The builders of the scenes built in code, under their registry names
(`datasets_gen.core.builtin_scenes`, which the command line reads without Blender)."""

from __future__ import annotations

from functools import partial
from typing import Callable

import bpy

from ..core.builtin_scenes import BUILTIN_SCENES
from .demo_scene import build_demo_scene
from .trap_scenes import (
    build_bright_object,
    build_glass_and_gloss,
    build_glass_dish,
    build_glass_over_checker,
    build_ground_plane,
    build_mirror_in_room,
    build_off_centre,
    build_rough_in_room,
    build_thin_film_coat,
    build_thin_structure,
)

BUILDERS: dict[str, Callable[[], bpy.types.Scene]] = {
    "demo": partial(build_demo_scene, variant=BUILTIN_SCENES["demo"].demo_variant),
    "demo_diffuse": partial(build_demo_scene, variant=BUILTIN_SCENES["demo_diffuse"].demo_variant),
    "bright_object": build_bright_object,
    "thin_structure": build_thin_structure,
    "off_centre": build_off_centre,
    "ground_plane": build_ground_plane,
    "glass_and_gloss": build_glass_and_gloss,
    "glass_over_checker": build_glass_over_checker,
    "mirror_in_room": build_mirror_in_room,
    "rough_in_room": build_rough_in_room,
    "thin_film_coat": build_thin_film_coat,
    "glass_dish": build_glass_dish,
}
assert BUILDERS.keys() == BUILTIN_SCENES.keys(), "every registered scene has a builder, and no other"


def build_builtin(name: str) -> bpy.types.Scene:
    """Create the built-in scene ``name`` in the current Blender session and return it."""
    return BUILDERS[name]()
