"""The scenes built in code, by name: the registry behind `--builtin NAME`, `--demo` and `--suite`.

Pure (no bpy): the command line lists and checks the names without waiting for Blender; each
scene's builder is Blender-side, in `datasets_gen.blender.builtin_scenes.BUILDERS` under the same name.

`demo` and `demo_diffuse` are the demo scene and its all-diffuse variant (`--demo` and
`--demo --demo-variant diffuse` are their shorthands).  The trap scenes each stand for a kind
of user scene a NeRF preset has failed on, for the benchmark suite (`python -m datasets_gen
--suite DIR`, then `python -m nerf_backend bench --suite DIR`).  The demo is modelled in the
protocol's frame (`--frame blender` by default); the trap scenes stand for users' scenes and
are fitted like them (`--frame fit` by default).

Each dataset records where it came from in `generator.settings.scene` and in the profile: the
demo as before (`{"source": "demo", "demo_variant": ...}`), the others as
`{"source": "builtin", "builtin": NAME}`; the profile's `builtin` names the scene either way.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional


@dataclass(frozen=True)
class BuiltinScene:
    """A scene built in code: its name, what it stands for, and the frame it is rendered in."""

    name: str
    what: str  # the scene and the failure class it stands for (shown by --help, the suite, the README)
    frame: str  # the default --frame: "blender" (modelled in the protocol frame) or "fit"
    demo_variant: Optional[str] = None  # for the demo scene: its variant

    def source_record(self) -> dict[str, Any]:
        """How a dataset records this scene as its source (`generator.settings.scene`)."""
        if self.demo_variant is not None:  # as the demo always has: its datasets stay resumable
            return {"source": "demo", "demo_variant": self.demo_variant}
        return {"source": "builtin", "builtin": self.name}


_SCENES = (
    BuiltinScene("demo", "the demo: pedestal, gold sphere, textured cube and cone, thin rod and ring",
                 "blender", demo_variant="standard"),
    BuiltinScene("demo_diffuse", "the demo with every material a Diffuse BSDF (nothing view-dependent)",
                 "blender", demo_variant="diffuse"),
    BuiltinScene("bright_object", "a large white sphere (about 60 % of every frame) with a thin dark groove, "
                 "on the transparent film: a large white object", "fit"),
    BuiltinScene("thin_structure", "a wire lattice and a thin ring on a rod, 1-2 pixels wide at 100x100, and a "
                 "small solid sphere: thin structures", "fit"),
    BuiltinScene("off_centre", "most of the mass in one corner of the bounding box, a small cube in the "
                 "opposite corner, the box centre empty: geometry far from its box's centre", "fit"),
    BuiltinScene("ground_plane", "a 12x12 ground plane with a few small objects on it: bounds set by "
                 "a large flat surface", "fit"),
    BuiltinScene("glass_and_gloss", "glass (transmission 1, IOR 1.45) and polished metal on a small diffuse "
                 "base: transparency and view dependence", "fit"),
    BuiltinScene("glass_over_checker", "a clear glass sphere on a checkerboard plate: the board refracted "
                 "through glass", "fit"),
    BuiltinScene("mirror_in_room", "a mirror-smooth metal sphere and torus under a tiled world: sharp "
                 "reflections", "fit"),
    BuiltinScene("rough_in_room", "mirror_in_room's objects with rough metal (roughness 0.45): blurred "
                 "reflections", "fit"),
    BuiltinScene("thin_film_coat", "a dark sphere and torus under a thin-film coat (Blender 4.2+): iridescence",
                 "fit"),
    BuiltinScene("glass_dish", "a thin-walled glass dish with a thin-film coat and olives in it (Blender 4.2+): "
                 "hollow glass", "fit"),
)

#: Every built-in scene by name.
BUILTIN_SCENES: dict[str, BuiltinScene] = {scene.name: scene for scene in _SCENES}
#: The scenes standing for a known failure class.
TRAP_SCENES: tuple[str, ...] = ("bright_object", "thin_structure", "off_centre", "ground_plane", "glass_and_gloss",
                                "glass_over_checker", "mirror_in_room", "rough_in_room", "thin_film_coat",
                                "glass_dish")
#: What `--suite` renders besides the given .blend files: the trap scenes and the demo.
SUITE_BUILTINS: tuple[str, ...] = TRAP_SCENES + ("demo",)


def demo_builtin(variant: str) -> str:
    """The name of the demo scene's variant (`--demo --demo-variant VARIANT`)."""
    for scene in _SCENES:
        if scene.demo_variant == variant:
            return scene.name
    raise ValueError(f"unknown demo variant {variant!r}")


def builtin_scene(name: str) -> BuiltinScene:
    """The registry entry of `name` (ValueError listing the names when there is none)."""
    try:
        return BUILTIN_SCENES[name]
    except KeyError:
        raise ValueError(f"unknown built-in scene {name!r} (one of {', '.join(BUILTIN_SCENES)})") from None
