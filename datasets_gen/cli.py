"""Command line of the dataset generator, shared by `python -m datasets_gen` and generate.py.

    python -m datasets_gen (SCENE.blend | --demo | --builtin NAME) --out DIR [options]
    python -m datasets_gen --suite DIR [--suite-scene SCENE.blend ...] [options]
    python -m datasets_gen --merge DIR
    blender -b [SCENE.blend] --python datasets_gen/generate.py -- [SCENE.blend | --demo] --out DIR [options]

`--demo` is `--builtin demo` and `--demo --demo-variant diffuse` is `--builtin demo_diffuse`.
Without SCENE.blend, --demo or --builtin, `blender -b SCENE.blend --python ...` renders the
file Blender opened.  Bad input exits with status 2 and a single line on stderr naming the file or flag.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable, NoReturn, Optional, Sequence

from .builtin_scenes import BUILTIN_SCENES
from .intrinsics import SENSOR_FITS, CameraSettings
from .options import (
    COLOR_MANAGEMENT,
    DEMO_VARIANTS,
    DEPTH_NORMALS,
    DEVICES,
    FRAMES,
    DatasetGenError,
    GeneratorOptions,
    Shard,
    parse_pixel_aspect,
)

PROG = "datasets_gen"
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
DEFAULT_CAMERA = CameraSettings()
#: Flags --use-scene-camera replaces (giving both would be ambiguous).
CAMERA_FLAGS = ("resolution", "width", "height", "resolution_percentage", "lens", "sensor_width",
                "sensor_height", "sensor_fit", "shift_x", "shift_y", "pixel_aspect")


class _OneLineParser(argparse.ArgumentParser):
    """argparse that reports errors as one line (no usage dump), like the rest of the CLI."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog=PROG,
        description="Render a NeRF dataset (nerf_synthetic / Realistic Synthetic 360 protocol) "
        "from a .blend file or a scene built in code. Defaults are the protocol's.",
    )
    parser.add_argument("scene", nargs="?", metavar="SCENE.blend", help="scene to render (or use --demo)")
    parser.add_argument("--demo", action="store_true",
                        help="render the built-in procedural demo scene (the same as --builtin demo)")
    parser.add_argument("--demo-variant", choices=DEMO_VARIANTS, default="standard",
                        help="standard, or diffuse: every demo material a Diffuse BSDF (default: standard; "
                        "--demo --demo-variant diffuse is --builtin demo_diffuse)")
    scenes = "; ".join(f"{scene.name}: {scene.what}" for scene in BUILTIN_SCENES.values())
    parser.add_argument("--builtin", choices=tuple(BUILTIN_SCENES), metavar="NAME",
                        help="render a scene built in code: " + scenes.replace("%", "%%"))
    parser.add_argument("--suite", metavar="DIR",
                        help="render the benchmark suite into DIR/NAME: every built-in trap scene, the demo and "
                        "each --suite-scene, with the other flags; complete datasets are kept, incomplete "
                        "ones resumed (no SCENE, --demo, --builtin or --out)")
    parser.add_argument("--suite-scene", action="append", default=[], metavar="SCENE.blend",
                        help="with --suite: also render this .blend into DIR/STEM (repeatable)")
    parser.add_argument("--out", metavar="DIR", help="output folder (must be empty or new)")
    parser.add_argument("--merge", metavar="DIR",
                        help="join the shard JSON files in DIR into the dataset's JSON (no SCENE, no --out)")
    parser.add_argument("--check", action="store_true",
                        help="run the scene checks and print the scene profile (JSON); render nothing")

    views = parser.add_argument_group("views (protocol: 100 / 100 / 200, upper hemisphere)")
    views.add_argument("--train-views", type=int, default=100, metavar="N", help="default: 100")
    views.add_argument("--val-views", type=int, default=100, metavar="N", help="default: 100")
    views.add_argument("--test-views", type=int, default=200, metavar="N",
                       help="default: 200 (the protocol's spiral; other counts keep its two turns)")
    views.add_argument("--sphere", action="store_true",
                       help="train/val views on the full sphere instead of the upper hemisphere")
    views.add_argument("--seed", type=int, default=0, help="seed of the random views and of Cycles (default: 0)")

    camera = parser.add_argument_group("camera (protocol: 800x800, 50 mm lens, 36 mm sensor, AUTO fit)")
    camera.add_argument("--resolution", type=int, metavar="N", help="square image size (default: 800)")
    camera.add_argument("--width", type=int, metavar="W", help="image width (with --height)")
    camera.add_argument("--height", type=int, metavar="H", help="image height (with --width)")
    camera.add_argument("--resolution-percentage", type=int, metavar="P", help="scales W and H (default: 100)")
    camera.add_argument("--pixel-aspect", metavar="X:Y", help="pixel aspect ratio (default: 1:1)")
    camera.add_argument("--lens", type=float, metavar="MM", help="focal length in mm (default: 50)")
    camera.add_argument("--sensor-width", type=float, metavar="MM", help="default: 36")
    camera.add_argument("--sensor-height", type=float, metavar="MM", help="default: 24")
    camera.add_argument("--sensor-fit", choices=SENSOR_FITS, help="default: AUTO")
    camera.add_argument("--shift-x", type=float, metavar="S", help="lens shift (default: 0)")
    camera.add_argument("--shift-y", type=float, metavar="S", help="lens shift (default: 0)")
    camera.add_argument("--use-scene-camera", action="store_true",
                        help="take lens, sensor, shift, resolution and pixel aspect from the .blend's active "
                        "camera and render settings (the poses stay the protocol's)")

    render = parser.add_argument_group("rendering")
    render.add_argument("--samples", type=int, default=128, metavar="N", help="Cycles samples (default: 128)")
    render.add_argument("--device", default="CPU", choices=DEVICES,
                        help="Cycles device; GPU = the first GPU backend with a device (default: CPU)")
    render.add_argument("--frame", choices=FRAMES,
                        help="fit: map the scene into the protocol's frame (default for .blend files); "
                        "blender: keep Blender's world (default for --demo)")
    render.add_argument("--depth-normals", choices=DEPTH_NORMALS, default="test",
                        help="float depth and normal EXRs for no split, the test split, or all (default: test)")
    render.add_argument("--color-management", choices=COLOR_MANAGEMENT, default="standard",
                        help="standard: the protocol's Standard/None/0/1; scene: keep the file's (default: standard)")
    render.add_argument("--allow-missing", action="store_true",
                        help="render although images, libraries or other files are missing (recorded)")

    run = parser.add_argument_group("long renders")
    run.add_argument("--overwrite", action="store_true", help="replace the dataset in a non-empty --out folder")
    run.add_argument("--resume", action="store_true",
                     help="keep the views already written and verified in --out, render the rest")
    run.add_argument("--shard", metavar="K/N", help="render only views with index %% N == K; then --merge")
    run.add_argument("--no-progress", action="store_true", help="do not show progress on stderr")
    return parser


def _camera_from_args(args: argparse.Namespace, parser: argparse.ArgumentParser) -> CameraSettings:
    if args.resolution is not None and (args.width is not None or args.height is not None):
        parser.error("argument --resolution: not allowed with --width/--height")
    if (args.width is None) != (args.height is None):
        parser.error("arguments --width and --height must be given together")
    if args.resolution is not None:
        width = height = args.resolution
    elif args.width is not None:
        width, height = args.width, args.height
    else:
        width, height = DEFAULT_CAMERA.resolution_x, DEFAULT_CAMERA.resolution_y
    aspect = (DEFAULT_CAMERA.pixel_aspect_x, DEFAULT_CAMERA.pixel_aspect_y)
    if args.pixel_aspect is not None:
        try:
            aspect = parse_pixel_aspect(args.pixel_aspect)
        except DatasetGenError as error:
            parser.error(str(error))

    def given(value: Optional[float], default: float) -> float:
        return default if value is None else value

    return CameraSettings(
        lens_mm=given(args.lens, DEFAULT_CAMERA.lens_mm),
        sensor_width_mm=given(args.sensor_width, DEFAULT_CAMERA.sensor_width_mm),
        sensor_height_mm=given(args.sensor_height, DEFAULT_CAMERA.sensor_height_mm),
        sensor_fit=args.sensor_fit or DEFAULT_CAMERA.sensor_fit,
        shift_x=given(args.shift_x, DEFAULT_CAMERA.shift_x),
        shift_y=given(args.shift_y, DEFAULT_CAMERA.shift_y),
        resolution_x=width,
        resolution_y=height,
        resolution_percentage=int(given(args.resolution_percentage, DEFAULT_CAMERA.resolution_percentage)),
        pixel_aspect_x=aspect[0],
        pixel_aspect_y=aspect[1],
    )


def options_from_args(
    args: argparse.Namespace, parser: argparse.ArgumentParser, blender_file: str = ""
) -> GeneratorOptions:
    """Turn parsed arguments into validated GeneratorOptions (errors through `parser.error`).

    `blender_file` is the file a `blender -b SCENE.blend` session opened: rendered when neither
    SCENE.blend nor --demo is given.
    """
    if args.use_scene_camera:
        given = [name for name in CAMERA_FLAGS if getattr(args, name) is not None]
        if given:
            parser.error(f"argument --{given[0].replace('_', '-')}: not allowed with --use-scene-camera")
    if not args.out and not args.check:
        parser.error("the following arguments are required: --out")
    shard = None
    if args.shard is not None:
        try:
            shard = Shard.parse(args.shard)
        except DatasetGenError as error:
            parser.error(str(error))
    open_scene = args.scene is None and not args.demo and args.builtin is None and bool(blender_file)
    options = GeneratorOptions(
        out_dir=args.out or "",
        demo=args.demo,
        demo_variant=args.demo_variant,
        builtin=args.builtin,
        blend_path=blender_file if open_scene else args.scene,
        open_scene=open_scene,
        train_views=args.train_views,
        val_views=args.val_views,
        test_views=args.test_views,
        camera=_camera_from_args(args, parser),
        use_scene_camera=args.use_scene_camera,
        samples=args.samples,
        seed=args.seed,
        full_sphere=args.sphere,
        device=args.device,
        frame=args.frame,
        depth_normals=args.depth_normals,
        allow_missing=args.allow_missing,
        color_management=args.color_management,
        overwrite=args.overwrite,
        resume=args.resume,
        shard=shard,
        check_only=args.check,
    )
    try:
        return options.validate()
    except DatasetGenError as error:
        parser.error(str(error))


def main(argv: Optional[Sequence[str]] = None, blender_file: str = "") -> int:
    """Run the CLI; return the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.merge is not None:
        extra = [flag for flag, value in (("SCENE.blend", args.scene), ("--demo", args.demo),
                                          ("--builtin", args.builtin), ("--out", args.out), ("--suite", args.suite))
                 if value]
        if extra:
            parser.error(f"--merge DIR takes no {extra[0]}")
        return _guarded(lambda: _merge(args.merge), args.merge)
    if args.suite is not None:
        return _suite(args, parser)
    if args.suite_scene:
        parser.error("--suite-scene needs --suite DIR")
    options = options_from_args(args, parser, blender_file)
    from .generator import run

    if options.check_only:  # the profile on stdout, for the user who asked (not for the add-on's calls)
        return _guarded(lambda: print(json.dumps(run(options, progress=False), indent=2)), options.out_dir, True)
    return _guarded(lambda: run(options, progress=not args.no_progress), options.out_dir)


def _suite(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """--suite DIR: the trap scenes, the demo and each --suite-scene, each into DIR/NAME."""
    from .builtin_scenes import SUITE_BUILTINS
    from .suite import plan_suite, run_suite

    extra = [flag for flag, value in (
        ("SCENE.blend", args.scene), ("--demo", args.demo), ("--builtin", args.builtin), ("--out", args.out),
        ("--check", args.check), ("--shard", args.shard), ("--demo-variant", args.demo_variant != "standard"),
    ) if value]
    if extra:
        parser.error(f"--suite DIR takes no {extra[0]} (it renders {', '.join(SUITE_BUILTINS)} and each --suite-scene)")
    # The shared flags are checked once, on the suite's first scene; each scene then gets its own.
    first = argparse.Namespace(**{**vars(args), "builtin": SUITE_BUILTINS[0], "out": args.suite})
    template = options_from_args(first, parser)
    try:
        plan = plan_suite(template, args.suite, args.suite_scene)
    except DatasetGenError as error:
        parser.error(str(error))
    statuses: list[int] = []
    failed = _guarded(lambda: statuses.append(run_suite(plan, progress=not args.no_progress)), args.suite,
                      quiet=True, interrupted=f"run the same command again to resume the suite in {args.suite}")
    return failed or statuses[0]


def _merge(out_dir: str) -> None:
    from .shards import merge

    merge(out_dir)


def _guarded(action: Callable[[], object], out_dir: str, quiet: bool = False, interrupted: str = "") -> int:
    """Run `action`, turning DatasetGenError, OSError and Ctrl-C into one line and an exit status
    (`interrupted`: what to say after Ctrl-C, instead of how to resume one dataset)."""
    try:
        action()
    except DatasetGenError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as error:  # e.g. a full disk or a folder without write permission
        where = f"{error.filename}: " if error.filename else ""
        print(f"{PROG}: error: {where}{error.strerror or error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; "
              f"{interrupted or f'{out_dir} holds no complete dataset (rerun with --resume to continue)'}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    if not quiet:
        print(f"{PROG}: wrote {out_dir}", file=sys.stderr)
    return 0
