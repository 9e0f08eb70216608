"""What a dataset generation run is asked to do, validated before Blender does any work.

Kept free of bpy so the CLI can reject bad input in a fraction of a second, and so the same
checks apply to the command line and to in-process callers (the add-on).  Every default is
the nerf_synthetic protocol's; each way of departing from it is one field (one flag).

`GeneratorOptions` is the one definition of the options: `SETTINGS` names each field's flag
and keyword, from which the CLI builds its parser (cli.py), `options_from_keywords` builds
options from keywords (generate_dataset, the CLI, the add-on), and `options_to_argv` writes
options as the command line that parses back into them (the add-on's background Blender).
"""

from __future__ import annotations

import difflib
import os
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Collection, Optional

from .builtin_scenes import BUILTIN_SCENES, demo_builtin
from .frame_fit import view_half_angle
from .intrinsics import SENSOR_FITS, CameraSettings

DEVICES = ("CPU", "GPU", "CUDA", "OPTIX", "HIP", "METAL", "ONEAPI")
FRAMES = ("fit", "blender")
DEPTH_NORMALS = ("none", "test", "all")
DEMO_VARIANTS = ("standard", "diffuse")
COLOR_MANAGEMENT = ("standard", "scene")
#: The layouts --format adds beside nerf_synthetic's, from the same render, with the label and
#: description the add-on's checkboxes show (io/formats.py writes them).
EXTRA_FORMATS: dict[str, tuple[str, str]] = {
    "colmap": ("COLMAP", "A COLMAP model of the training views (cameras, poses, images, masks) with the scene's "
                         "surface points, and points3d.ply, as 3DGS, gsplat and nerfstudio read them"),
    "ngp": ("NGP", "Instant-NGP's layout: one transforms.json of every split, as Instant-NGP and nerfstudio read it"),
}
#: Dataset layouts: nerf_synthetic's transforms_{split}.json are always written (the dataset's
#: own record); --format adds the others.
FORMATS = ("nerf_synthetic", *EXTRA_FORMATS)


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
    formats: tuple[str, ...] = ()  # layouts written besides nerf_synthetic's (FORMATS)

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
        for name in self.formats:
            _choice(name, FORMATS, "--format")
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


# ---------------------------------------------------------------- the options as flags and keywords

DEFAULT_OPTIONS = GeneratorOptions(out_dir="")
_DEFAULT_CAMERA = DEFAULT_OPTIONS.camera

#: The --help sections, in order ("" is the top level).
GROUPS = (
    "",
    f"views (protocol: {DEFAULT_OPTIONS.train_views} / {DEFAULT_OPTIONS.val_views} / "
    f"{DEFAULT_OPTIONS.test_views}, upper hemisphere)",
    f"camera (protocol: {_DEFAULT_CAMERA.resolution_x}x{_DEFAULT_CAMERA.resolution_y}, "
    f"{_DEFAULT_CAMERA.lens_mm:g} mm lens, {_DEFAULT_CAMERA.sensor_width_mm:g} mm sensor, "
    f"{_DEFAULT_CAMERA.sensor_fit} fit)",
    "rendering",
    "long renders",
)
_SCENE, _VIEWS, _CAMERA, _RENDERING, _LONG = GROUPS


@dataclass(frozen=True)
class Setting:
    """One option: its keyword, the GeneratorOptions field(s) it sets and its command-line flag.

    The keyword is `generate_dataset`'s and the parsed argument's name.  `fields` default to
    the keyword; "camera.lens_mm" is a field of the camera; two fields (the pixel aspect) make
    the value a pair.  `flag`: "--name", a positional's metavar ("SCENE.blend"), or None (no
    flag).  `kind`: bool for a switch (its flag turns it on), else the type of the flag's value;
    `parse` turns the flag's text (or a keyword given as text) into the value, raising
    DatasetGenError, and `text` the value into the flag's text.  In `help`, "{default}" is the
    field's default.
    """

    keyword: str
    flag: Optional[str]
    help: str = ""
    group: str = _SCENE
    kind: type = str
    choices: tuple[str, ...] = ()
    metavar: Optional[str] = None
    fields: tuple[str, ...] = ()
    parse: Optional[Callable[[str], Any]] = None
    text: Callable[[Any], str] = str
    repeatable: bool = False  # the flag may be given again; the value is then a tuple of them

    @property
    def targets(self) -> tuple[str, ...]:
        return self.fields or (self.keyword,)

    @property
    def positional(self) -> bool:
        return self.flag is not None and not self.flag.startswith("-")

    @property
    def is_camera(self) -> bool:
        return self.targets[0].startswith("camera.")

    def value(self, options: GeneratorOptions) -> Any:
        """This setting's value in `options` (a tuple for two fields)."""
        values = tuple(_field_value(options, name) for name in self.targets)
        return values[0] if len(values) == 1 else values

    @property
    def default(self) -> Any:
        return self.value(DEFAULT_OPTIONS)

    def help_text(self) -> str:
        return self.help.replace("{default}", _shown(self.default))

    def argv(self, value: Any) -> list[str]:
        """The command line stating `value` (a switch's is its flag alone)."""
        if self.repeatable:
            return [word for item in value for word in (self.flag, item)]
        if self.kind is bool:
            return [self.flag] if value else []
        return [self.text(value)] if self.positional else [self.flag, self.text(value)]

    def field_values(self, value: Any) -> dict[str, Any]:
        """`value` (as a keyword gives it) as field name → value; text is parsed ("" is the default)."""
        if self.parse is not None and isinstance(value, str):
            value = self.parse(value) if value else self.default
        elif self.repeatable and self.parse is not None:  # a list or tuple, as the add-on gives it
            value = self.parse(",".join(value))
        if len(self.targets) == 1:
            return {self.targets[0]: value}
        values = tuple(value)
        if len(values) != len(self.targets):
            raise TypeError(f"dataset option {self.keyword!r} takes {len(self.targets)} values, got {value!r}")
        return dict(zip(self.targets, values))


def parse_formats(text: str) -> tuple[str, ...]:
    """``"ngp,nerf_synthetic"`` (the flags given, joined by commas) as the extra layouts, in
    order, each once; nerf_synthetic's are always written, so it is not kept."""
    names: list[str] = []
    for name in (part.strip() for part in text.split(",")):
        if not name:
            continue
        _choice(name, FORMATS, "--format")
        if name != "nerf_synthetic" and name not in names:
            names.append(name)
    return tuple(names)


def _field_value(options: GeneratorOptions, name: str) -> Any:
    value: Any = options
    for part in name.split("."):
        value = getattr(value, part)
    return value


def _shown(value: Any) -> str:
    """A default as --help shows it: 50 mm, not 50.0; 1:1 for the pixel aspect."""
    if isinstance(value, tuple):
        return ":".join(_shown(part) for part in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def _decimal(value: float) -> str:
    """A float as --pixel-aspect reads it back exactly (no exponent)."""
    text = repr(float(value))
    return text if "e" not in text else f"{value:.20f}".rstrip("0").rstrip(".")


_BUILTINS_HELP = "; ".join(f"{scene.name}: {scene.what}" for scene in BUILTIN_SCENES.values())

#: Every option, in --help order within its group.  The camera settings come in the order that
#: --use-scene-camera names the first one given.
SETTINGS: tuple[Setting, ...] = (
    # The scene: exactly one source (open_scene has no flag: it is the file Blender opened, or
    # the add-on's open scene).
    Setting("blend_path", "SCENE.blend", "scene to render (or use --demo)"),
    Setting("demo", "--demo", "render the built-in procedural demo scene (the same as --builtin demo)", kind=bool),
    Setting("demo_variant", "--demo-variant", "standard, or diffuse: every demo material a Diffuse BSDF "
            "(default: {default}; --demo --demo-variant diffuse is --builtin demo_diffuse)", choices=DEMO_VARIANTS),
    Setting("builtin", "--builtin", "render a scene built in code: " + _BUILTINS_HELP,
            choices=tuple(BUILTIN_SCENES), metavar="NAME"),
    Setting("open_scene", None, kind=bool),
    Setting("out_dir", "--out", "output folder (must be empty or new)", metavar="DIR"),
    Setting("check_only", "--check", "run the scene checks and print the scene profile (JSON); render nothing",
            kind=bool),
    # Views.
    Setting("train_views", "--train-views", "default: {default}", _VIEWS, int, metavar="N"),
    Setting("val_views", "--val-views", "default: {default}", _VIEWS, int, metavar="N"),
    Setting("test_views", "--test-views", "default: {default} (the protocol's spiral; other counts keep its two turns)",
            _VIEWS, int, metavar="N"),
    Setting("full_sphere", "--sphere", "train/val views on the full sphere instead of the upper hemisphere",
            _VIEWS, bool),
    Setting("seed", "--seed", "seed of the random views and of Cycles (default: {default})", _VIEWS, int),
    # The camera (--resolution N, the CLI's shorthand for --width N --height N, is in cli.py).
    Setting("width", "--width", "image width (with --height)", _CAMERA, int, metavar="W",
            fields=("camera.resolution_x",)),
    Setting("height", "--height", "image height (with --width)", _CAMERA, int, metavar="H",
            fields=("camera.resolution_y",)),
    Setting("resolution_percentage", "--resolution-percentage", "scales W and H (default: {default})", _CAMERA, int,
            metavar="P", fields=("camera.resolution_percentage",)),
    Setting("lens", "--lens", "focal length in mm (default: {default})", _CAMERA, float, metavar="MM",
            fields=("camera.lens_mm",)),
    Setting("sensor_width", "--sensor-width", "default: {default}", _CAMERA, float, metavar="MM",
            fields=("camera.sensor_width_mm",)),
    Setting("sensor_height", "--sensor-height", "default: {default}", _CAMERA, float, metavar="MM",
            fields=("camera.sensor_height_mm",)),
    Setting("sensor_fit", "--sensor-fit", "default: {default}", _CAMERA, choices=SENSOR_FITS,
            fields=("camera.sensor_fit",)),
    Setting("shift_x", "--shift-x", "lens shift (default: {default})", _CAMERA, float, metavar="S",
            fields=("camera.shift_x",)),
    Setting("shift_y", "--shift-y", "lens shift (default: {default})", _CAMERA, float, metavar="S",
            fields=("camera.shift_y",)),
    Setting("pixel_aspect", "--pixel-aspect", "pixel aspect ratio (default: {default})", _CAMERA, metavar="X:Y",
            fields=("camera.pixel_aspect_x", "camera.pixel_aspect_y"), parse=parse_pixel_aspect,
            text=lambda pair: f"{_decimal(pair[0])}:{_decimal(pair[1])}"),
    Setting("use_scene_camera", "--use-scene-camera", "take lens, sensor, shift, resolution and pixel aspect from "
            "the .blend's active camera and render settings (the poses stay the protocol's)", _CAMERA, bool),
    # Rendering.
    Setting("samples", "--samples", "Cycles samples (default: {default})", _RENDERING, int, metavar="N"),
    Setting("device", "--device", "Cycles device; GPU = the first GPU backend with a device (default: {default})",
            _RENDERING, choices=DEVICES),
    Setting("frame", "--frame", "fit: map the scene into the protocol's frame (default for .blend files); "
            "blender: keep Blender's world (default for --demo)", _RENDERING, choices=FRAMES),
    Setting("depth_normals", "--depth-normals", "float depth and normal EXRs for no split, the test split, or all "
            "(default: {default})", _RENDERING, choices=DEPTH_NORMALS),
    Setting("color_management", "--color-management", "standard: the protocol's Standard/None/0/1; scene: keep the "
            "file's (default: {default})", _RENDERING, choices=COLOR_MANAGEMENT),
    Setting("allow_missing", "--allow-missing", "render although images, libraries or other files are missing "
            "(recorded)", _RENDERING, bool),
    # Long renders.
    Setting("overwrite", "--overwrite", "replace the dataset in a non-empty --out folder", _LONG, bool),
    Setting("resume", "--resume", "keep the views already written and verified in --out, render the rest", _LONG, bool),
    Setting("shard", "--shard", "render only views with index % N == K; then --merge", _LONG, metavar="K/N",
            parse=Shard.parse, text=lambda shard: f"{shard.index}/{shard.count}"),
    Setting("formats", "--format", "also write the dataset in this layout, from the same render (repeatable): "
            "colmap, a COLMAP model of the training views with surface points, and points3d.ply (3DGS, gsplat); "
            "ngp, one transforms.json for Instant-NGP and nerfstudio (nerf_synthetic's files are always written)",
            _SCENE, metavar="NAME", parse=parse_formats, repeatable=True),
)
SETTINGS_BY_KEYWORD = {setting.keyword: setting for setting in SETTINGS}


def options_from_keywords(**keywords: Any) -> GeneratorOptions:
    """GeneratorOptions from settings given by keyword (`SETTINGS`: train_views=10, width=64,
    lens=35.0, pixel_aspect=(2, 1), shard="0/4", ...); the others keep their defaults.

    Not validated (see GeneratorOptions.validate).  TypeError names an unknown keyword;
    DatasetGenError a setting given as text that does not parse (shard="4/4").
    """
    values: dict[str, Any] = {"out_dir": ""}
    for keyword, value in keywords.items():
        setting = SETTINGS_BY_KEYWORD.get(keyword)
        if setting is None:
            raise TypeError(_unknown_keyword(keyword))
        values.update(setting.field_values(value))
    camera = {name.removeprefix("camera."): value for name, value in values.items() if name.startswith("camera.")}
    top = {name: value for name, value in values.items() if not name.startswith("camera.")}
    return GeneratorOptions(camera=CameraSettings(**camera), **top)


def _unknown_keyword(keyword: str) -> str:
    close = difflib.get_close_matches(keyword, SETTINGS_BY_KEYWORD, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown dataset option {keyword!r}{hint} (the options: {', '.join(SETTINGS_BY_KEYWORD)})"


def options_to_argv(options: GeneratorOptions, omit: Collection[str] = ()) -> list[str]:
    """The command line (after the program's name) that the CLI parses back into `options`:
    the flags of the settings that differ from the defaults, SCENE.blend first.

    `omit`: keywords of settings the caller states itself (DatasetJob adds --out; "width"
    omits the image size).  An open
    scene (`open_scene`) has no flag: it is the file the Blender running the CLI opened.
    ValueError for a camera with `use_scene_camera`, which the CLI refuses (the scene's
    camera replaces it).
    """
    if options.use_scene_camera and options.camera != _DEFAULT_CAMERA:
        raise ValueError("use_scene_camera takes the camera from the scene: camera settings would be refused")
    argv: list[str] = []
    for setting in SETTINGS:
        if setting.flag is None or setting.keyword in omit or setting.keyword == "height":
            continue
        if setting.keyword == "width":  # the image size: --resolution N, or --width W and --height H together
            argv += _size_argv(options.camera)
            continue
        if setting.keyword == "blend_path" and options.open_scene:
            continue  # the file Blender opened: not a flag
        value = setting.value(options)
        if value != setting.default:
            words = setting.argv(value)
            argv = [*words, *argv] if setting.positional else [*argv, *words]
    return argv


def _size_argv(camera: CameraSettings) -> list[str]:
    """--resolution N for a square size, else --width W --height H (the CLI wants both)."""
    size = (camera.resolution_x, camera.resolution_y)
    if size == (_DEFAULT_CAMERA.resolution_x, _DEFAULT_CAMERA.resolution_y):
        return []
    if size[0] == size[1]:
        return ["--resolution", str(size[0])]
    return ["--width", str(size[0]), "--height", str(size[1])]
