"""What a dataset generation run is asked to do, validated before Blender does any work.

Kept free of bpy so the CLI can reject bad input in a fraction of a second, and so the same
checks apply to the command line and to in-process callers (the add-on).  Every default is
the nerf_synthetic protocol's; each way of departing from it is one field (one flag).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from typing import Any, Optional

from .builtin_scenes import BUILTIN_SCENES, demo_builtin
from .frame_fit import view_half_angle
from .intrinsics import SENSOR_FITS, CameraSettings

DEVICES = ("CPU", "GPU", "CUDA", "OPTIX", "HIP", "METAL", "ONEAPI")
SPLITS = ("train", "val", "test")
FRAMES = ("fit", "blender")
DEPTH_NORMALS = ("none", "test", "all")
DEMO_VARIANTS = ("standard", "diffuse")
COLOR_MANAGEMENT = ("standard", "scene")


class DatasetGenError(Exception):
    """A problem with the user's input or environment, reported as one line without a traceback."""


@dataclass(frozen=True)
class Shard:
    """Views with global index % count == index, of every split (one machine of `count`)."""

    index: int
    count: int

    @classmethod
    def parse(cls, text: str) -> "Shard":
        match = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
        if not match:
            raise DatasetGenError(f"--shard must look like K/N (e.g. 0/4), got {text!r}")
        shard = cls(int(match.group(1)), int(match.group(2)))
        if shard.count < 1 or not 0 <= shard.index < shard.count:
            raise DatasetGenError(f"--shard K/N needs N >= 1 and 0 <= K < N, got {text!r}")
        return shard

    def owns(self, view_index: int) -> bool:
        return view_index % self.count == self.index

    @property
    def label(self) -> str:
        """As used in file names: shard-K-of-N."""
        return f"shard-{self.index}-of-{self.count}"


@dataclass(frozen=True)
class GeneratorOptions:
    """Settings of one run; defaults are the nerf_synthetic protocol's.

    Exactly one scene source: `builtin` (a scene built in code, see builtin_scenes), `demo`
    (shorthand for the builtin "demo", or "demo_diffuse" with `demo_variant` "diffuse"),
    `blend_path`, or `open_scene` (the scene already open in this Blender session: the add-on).
    `blend_path` with `open_scene` means that file is already open as loaded from disk
    (`blender -b SCENE.blend --python generate.py`): it is not reopened.
    `frame` None means "fit" for a user's scene and the built-in scene's own default for a
    built-in one (the identity for the demo, modelled in the protocol frame).
    """

    out_dir: str
    demo: bool = False
    demo_variant: str = "standard"
    builtin: Optional[str] = None
    blend_path: Optional[str] = None
    open_scene: bool = False
    train_views: int = 100
    val_views: int = 100
    test_views: int = 200
    camera: CameraSettings = field(default_factory=CameraSettings)
    use_scene_camera: bool = False
    samples: int = 128
    seed: int = 0
    full_sphere: bool = False
    device: str = "CPU"
    frame: Optional[str] = None
    depth_normals: str = "test"
    allow_missing: bool = False
    color_management: str = "standard"
    overwrite: bool = False
    resume: bool = False
    shard: Optional[Shard] = None
    check_only: bool = False

    def views(self, split: str) -> int:
        """Number of views of a split."""
        return {"train": self.train_views, "val": self.val_views, "test": self.test_views}[split]

    @property
    def builtin_name(self) -> Optional[str]:
        """The built-in scene rendered (`--demo` is the builtin "demo" or "demo_diffuse"), or None."""
        if self.demo:
            return demo_builtin(self.demo_variant) if self.demo_variant in DEMO_VARIANTS else None
        return self.builtin

    @property
    def frame_mode(self) -> str:
        """"fit" or "blender", with the default resolved."""
        if self.frame is not None:
            return self.frame
        name = self.builtin_name
        return BUILTIN_SCENES[name].frame if name in BUILTIN_SCENES else "fit"

    def wants_depth_normals(self, split: str) -> bool:
        return self.depth_normals == "all" or (self.depth_normals == "test" and split == "test")

    def validate(self) -> "GeneratorOptions":
        """Raise DatasetGenError naming the offending option; return self when all is well."""
        sources = int(self.demo) + int(self.builtin is not None) + int(self.blend_path is not None or self.open_scene)
        if sources != 1:
            raise DatasetGenError("give exactly one of SCENE.blend, --demo or --builtin NAME")
        if self.builtin is not None:
            _choice(self.builtin, tuple(BUILTIN_SCENES), "--builtin")
        if self.blend_path is not None:
            if not os.path.isfile(self.blend_path):
                raise DatasetGenError(f"scene file not found: {self.blend_path}")
            if not self.blend_path.lower().endswith(".blend"):
                raise DatasetGenError(f"scene file is not a .blend file: {self.blend_path}")
        _choice(self.demo_variant, DEMO_VARIANTS, "--demo-variant")
        _require(self.demo or self.demo_variant == "standard", "--demo-variant needs --demo")
        _require(self.train_views >= 1, f"--train-views must be >= 1, got {self.train_views}")
        _require(self.val_views >= 0, f"--val-views must be >= 0, got {self.val_views}")
        _require(self.test_views >= 0, f"--test-views must be >= 0, got {self.test_views}")
        _require(self.samples >= 1, f"--samples must be >= 1, got {self.samples}")
        _require(0 <= self.seed < 2**31, f"--seed must be in [0, 2^31), got {self.seed}")
        _choice(self.device, DEVICES, "--device")
        if self.frame is not None:
            _choice(self.frame, FRAMES, "--frame")
        _choice(self.depth_normals, DEPTH_NORMALS, "--depth-normals")
        _choice(self.color_management, COLOR_MANAGEMENT, "--color-management")
        _require(not (self.resume and self.overwrite), "--resume and --overwrite exclude each other")
        _require(bool(self.out_dir) or self.check_only, "--out must name a folder")
        if not self.use_scene_camera:
            validate_camera(self.camera)
        return self


def validate_camera(camera: CameraSettings) -> None:
    """Raise DatasetGenError naming the flag of the first invalid camera setting."""
    _require(
        1 <= camera.resolution_x <= 16384 and 1 <= camera.resolution_y <= 16384,
        f"resolution must be between 1 and 16384 pixels, got {camera.resolution_x}x{camera.resolution_y}",
    )
    _require(1 <= camera.resolution_percentage <= 1000,
             f"--resolution-percentage must be in 1..1000, got {camera.resolution_percentage}")
    _require(camera.lens_mm > 0, f"--lens must be > 0 mm, got {camera.lens_mm}")
    _require(camera.sensor_width_mm > 0, f"--sensor-width must be > 0 mm, got {camera.sensor_width_mm}")
    _require(camera.sensor_height_mm > 0, f"--sensor-height must be > 0 mm, got {camera.sensor_height_mm}")
    _choice(camera.sensor_fit, SENSOR_FITS, "--sensor-fit")
    _require(camera.pixel_aspect_x > 0 and camera.pixel_aspect_y > 0,
             f"--pixel-aspect must be positive, got {camera.pixel_aspect_x}:{camera.pixel_aspect_y}")
    _require(abs(camera.shift_x) <= 10 and abs(camera.shift_y) <= 10, "--shift-x/--shift-y must be within [-10, 10]")
    try:
        intrinsics = camera.intrinsics()
        # The protocol aims every camera's optical axis at the origin: it must cross the image.
        view_half_angle(intrinsics)
    except ValueError as error:
        raise DatasetGenError(f"camera settings: {error}") from None
    _require(intrinsics.w >= 1 and intrinsics.h >= 1,
             f"--resolution-percentage {camera.resolution_percentage} leaves no pixels")


def parse_pixel_aspect(text: str) -> tuple[float, float]:
    """"X:Y" -> (X, Y) for --pixel-aspect."""
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*:\s*([0-9]*\.?[0-9]+)\s*", text)
    if not match:
        raise DatasetGenError(f"--pixel-aspect must look like X:Y (e.g. 1:1 or 2:1), got {text!r}")
    x, y = float(match.group(1)), float(match.group(2))
    _require(x > 0 and y > 0, f"--pixel-aspect must be positive, got {text!r}")
    return x, y


def _choice(value: Any, choices: tuple, flag: str) -> None:
    _require(value in choices, f"{flag} must be one of {', '.join(choices)}, got {value}")


def _require(condition: bool, message: str) -> None:
    if not condition:
        raise DatasetGenError(message)
