"""Command line of the dataset generator, shared by `python -m datasets_gen` and generate.py.

    python -m datasets_gen (SCENE.blend | --demo | --builtin NAME) --out DIR [options]
    python -m datasets_gen --suite DIR [--suite-scene SCENE.blend ...] [options]
    python -m datasets_gen --merge DIR
    python -m datasets_gen SCENE.blend --out DATASET --camera-path CAMERA [--frames S:E[:STEP]] [--with-cycles]
    blender -b [SCENE.blend] --python datasets_gen/generate.py -- [SCENE.blend | --demo] --out DIR [options]

`--demo` is `--builtin demo` and `--demo --demo-variant diffuse` is `--builtin demo_diffuse`.
Without SCENE.blend, --demo or --builtin, `blender -b SCENE.blend --python ...` renders the
file Blender opened.  Bad input exits with status 2 and a single line on stderr naming the file or flag.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Callable, NoReturn, Optional, Sequence

from nerf_contract.commands import GeneratorFlag
from nerf_contract.run_layout import ASSET_ENGINES

from .core.options import (
    DEFAULT_OPTIONS,
    GROUPS,
    SETTINGS,
    DatasetGenError,
    GeneratorOptions,
    Setting,
    options_from_keywords,
)

PROG = "datasets_gen"
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
_CAMERA_GROUP, _LONG_RENDERS_GROUP = GROUPS[2], GROUPS[4]


class _OneLineParser(argparse.ArgumentParser):
    """argparse that reports errors as one line (no usage dump), like the rest of the CLI."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The options' flags (options.SETTINGS, each parsed into its keyword; None when not given,
    so that the defaults stay GeneratorOptions') and the CLI's own: --resolution, --suite,
    --suite-scene, --merge and --no-progress."""
    parser = _OneLineParser(
        prog=PROG,
        description="Render a NeRF dataset (nerf_synthetic / Realistic Synthetic 360 protocol) "
        "from a .blend file or a scene built in code. Defaults are the protocol's.",
    )
    groups = {title: parser.add_argument_group(title) if title else parser for title in GROUPS}
    groups[_CAMERA_GROUP].add_argument(
        "--resolution", type=int, metavar="N",
        help=f"square image size (default: {DEFAULT_OPTIONS.camera.resolution_x}; --width N --height N)")
    for setting in SETTINGS:
        if setting.flag is not None:
            _add_setting(groups[setting.group], setting)
    parser.add_argument("--suite", metavar="DIR",
                        help="render the benchmark suite into DIR/NAME: every built-in trap scene, the demo and "
                        "each --suite-scene, with the other flags; complete datasets are kept, incomplete "
                        "ones resumed (no SCENE, --demo, --builtin or --out)")
    parser.add_argument("--suite-scene", action="append", default=[], metavar="SCENE.blend",
                        help="with --suite: also render this .blend into DIR/STEM (repeatable)")
    parser.add_argument("--merge", metavar="DIR",
                        help="join the shard JSON files in DIR into the dataset's JSON (no SCENE, no --out)")
    groups[_LONG_RENDERS_GROUP].add_argument(GeneratorFlag.NO_PROGRESS, action="store_true",
                                             help="do not show progress on stderr")
    asset = parser.add_argument_group("a baked NeRF asset (python -m nerf_backend export), scored like the NeRF")
    asset.add_argument(GeneratorFlag.RENDER_ASSET, metavar="ASSET.glb",
                       help="render the asset alone from the test cameras of --dataset, as its views were rendered, "
                       "into --out DIR/STEM.png (for python -m nerf_backend eval --dataset DATASET --renders DIR)")
    asset.add_argument(GeneratorFlag.DATASET, metavar="DATASET", help="with --render-asset: the dataset whose cameras")
    asset.add_argument(GeneratorFlag.ENGINE, choices=ASSET_ENGINES, default=ASSET_ENGINES[0],
                       help="with --render-asset: the render engine (default: cycles)")
    path = parser.add_argument_group("camera animation (for python -m nerf_backend render RUN --camera-path)")
    path.add_argument(GeneratorFlag.CAMERA_PATH, metavar="CAMERA",
                      help="write CAMERA's animation as a camera path in the NeRF frame of the dataset in --out "
                      "(which must exist) into DATASET/camera_paths/CAMERA/camera_path.json; frames have the scene's render "
                      "size, scaled by --resolution-percentage P when given")
    path.add_argument(GeneratorFlag.FRAMES, metavar="S:E[:STEP]",
                      help="with --camera-path: the frames, both ends included (default: the scene's frame range)")
    # Not "--cycles": Blender's Cycles add-on parses the arguments after "--" too, and takes any
    # prefix of its --cycles-device and --cycles-print-stats as ambiguous (the run then stops).
    path.add_argument(GeneratorFlag.WITH_CYCLES, dest="cycles", action="store_true",
                      help="with --camera-path: also render those frames with Cycles, with the dataset's settings "
                      "(frames already rendered are kept)")
    return parser


def _add_setting(group: argparse._ActionsContainer, setting: Setting) -> None:
    help_text = setting.help_text().replace("%", "%%")  # argparse %-formats help
    if setting.positional:
        group.add_argument(setting.keyword, nargs="?", metavar=setting.flag, help=help_text)
    elif setting.repeatable:  # each flag's text, joined by commas for `parse`
        group.add_argument(setting.flag, dest=setting.keyword, action="append", metavar=setting.metavar,
                           help=help_text)
    elif setting.kind is bool:
        group.add_argument(setting.flag, dest=setting.keyword, action="store_true", default=None, help=help_text)
    else:  # text that `parse` reads is parsed after argparse, so that its error is the option's own line
        group.add_argument(setting.flag, dest=setting.keyword, type=str if setting.parse else setting.kind,
                           choices=setting.choices or None, metavar=setting.metavar, help=help_text)


def _given(args: argparse.Namespace) -> dict[str, Any]:
    """The settings the command line states, by keyword."""
    given = {setting.keyword: getattr(args, setting.keyword) for setting in SETTINGS
             if setting.flag is not None and getattr(args, setting.keyword) is not None}
    return {keyword: ",".join(value) if isinstance(value, list) else value for keyword, value in given.items()}


def _image_size(args: argparse.Namespace, parser: argparse.ArgumentParser) -> dict[str, int]:
    """--resolution N is --width N --height N; --width and --height go together."""
    if args.resolution is not None and (args.width is not None or args.height is not None):
        parser.error("argument --resolution: not allowed with --width/--height")
    if (args.width is None) != (args.height is None):
        parser.error("arguments --width and --height must be given together")
    return {} if args.resolution is None else {"width": args.resolution, "height": args.resolution}


def options_from_args(
    args: argparse.Namespace, parser: argparse.ArgumentParser, blender_file: str = ""
) -> GeneratorOptions:
    """Turn parsed arguments into validated GeneratorOptions (errors through `parser.error`).

    `blender_file` is the file a `blender -b SCENE.blend` session opened: rendered when neither
    SCENE.blend nor --demo is given.
    """
    given = _given(args)
    if given.get("use_scene_camera"):
        camera = ["--resolution"] * (args.resolution is not None) + [
            setting.flag for setting in SETTINGS if setting.is_camera and setting.keyword in given]
        if camera:
            parser.error(f"argument {camera[0]}: not allowed with --use-scene-camera")
    if not given.get("out_dir") and not given.get("check_only"):
        parser.error("the following arguments are required: --out")
    given.update(_image_size(args, parser))
    if "blend_path" not in given and not given.get("demo") and "builtin" not in given and blender_file:
        given.update(blend_path=blender_file, open_scene=True)
    try:
        return options_from_keywords(**given).validate()
    except DatasetGenError as error:
        parser.error(str(error))


def main(argv: Optional[Sequence[str]] = None, blender_file: str = "") -> int:
    """Run the CLI; return the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.merge is not None:
        extra = [flag for flag, value in (("SCENE.blend", args.blend_path), ("--demo", args.demo),
                                          ("--builtin", args.builtin), ("--out", args.out_dir), ("--suite", args.suite))
                 if value]
        if extra:
            parser.error(f"--merge DIR takes no {extra[0]}")
        return _guarded(lambda: _merge(args.merge), args.merge)
    if args.suite is not None:
        return _suite(args, parser)
    if args.render_asset is not None:
        return _render_asset(args, parser)
    if args.dataset is not None:
        parser.error(f"{GeneratorFlag.DATASET} needs {GeneratorFlag.RENDER_ASSET} ASSET.glb")
    if args.camera_path is None and (args.frames is not None or args.cycles):
        flag = GeneratorFlag.FRAMES if args.frames is not None else GeneratorFlag.WITH_CYCLES
        parser.error(f"argument {flag}: needs {GeneratorFlag.CAMERA_PATH} CAMERA")
    if args.camera_path is not None:
        return _camera_path(args, parser, blender_file)
    if args.suite_scene:
        parser.error("--suite-scene needs --suite DIR")
    options = options_from_args(args, parser, blender_file)
    from .generator import run

    if options.check_only:  # the profile on stdout, for the user who asked (not for the add-on's calls)
        return _guarded(lambda: print(json.dumps(run(options, progress=False), indent=2)), options.out_dir, True)
    return _guarded(lambda: run(options, progress=not args.no_progress), options.out_dir)


def _suite(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """--suite DIR: the trap scenes, the demo and each --suite-scene, each into DIR/NAME."""
    from .core.builtin_scenes import SUITE_BUILTINS
    from .suite import plan_suite, run_suite

    extra = [flag for flag, value in (
        ("SCENE.blend", args.blend_path), ("--demo", args.demo), ("--builtin", args.builtin), ("--out", args.out_dir),
        ("--check", args.check_only), ("--shard", args.shard),
        ("--demo-variant", args.demo_variant not in (None, DEFAULT_OPTIONS.demo_variant)),
    ) if value]
    if extra:
        parser.error(f"--suite DIR takes no {extra[0]} (it renders {', '.join(SUITE_BUILTINS)} and each --suite-scene)")
    # The shared flags are checked once, on the suite's first scene; each scene then gets its own.
    first = argparse.Namespace(**{**vars(args), "builtin": SUITE_BUILTINS[0], "out_dir": args.suite})
    template = options_from_args(first, parser)
    try:
        plan = plan_suite(template, args.suite, args.suite_scene)
    except DatasetGenError as error:
        parser.error(str(error))
    statuses: list[int] = []
    failed = _guarded(lambda: statuses.append(run_suite(plan, progress=not args.no_progress)), args.suite,
                      quiet=True, interrupted=f"run the same command again to resume the suite in {args.suite}")
    return failed or statuses[0]


def _camera_path(args: argparse.Namespace, parser: argparse.ArgumentParser, blender_file: str) -> int:
    """--camera-path CAMERA: the animation of a camera into the dataset in --out."""
    from .camera_path_export import export_from_options
    from .core.camera_path import parse_frames

    options = options_from_args(args, parser, blender_file)
    if args.frames is not None:
        try:
            parse_frames(args.frames)
        except DatasetGenError as error:
            parser.error(str(error))
    written: list[str] = []
    status = _guarded(lambda: written.append(export_from_options(
        options, args.camera_path, args.frames, args.cycles, progress=not args.no_progress,
        resolution_percentage=args.resolution_percentage)), options.out_dir,
        quiet=True, interrupted="run the same command again to keep the Cycles frames rendered and render the rest")
    if not status:
        print(f"{PROG}: wrote {written[0]}", file=sys.stderr)
    return status


def _render_asset(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    """--render-asset ASSET.glb --dataset DATASET --out DIR: the asset from the dataset's test cameras."""
    from .asset_render import render_asset

    extra = [flag for flag, value in (("SCENE.blend", args.blend_path), ("--demo", args.demo),
                                      ("--builtin", args.builtin), ("--camera-path", args.camera_path)) if value]
    if extra:
        parser.error(f"{GeneratorFlag.RENDER_ASSET} takes no {extra[0]}: the asset is rendered alone")
    if args.dataset is None or args.out_dir is None:
        parser.error(f"{GeneratorFlag.RENDER_ASSET} needs {GeneratorFlag.DATASET} DATASET and --out DIR")
    return _guarded(lambda: render_asset(args.render_asset, args.dataset, args.out_dir, args.engine,
                                         device=args.device or "CPU", progress=not args.no_progress), args.out_dir,
                    quiet=True)


def _merge(out_dir: str) -> None:
    from .io.shards import merge

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
