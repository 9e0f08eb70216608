"""Command line of the dataset generator, shared by `python -m datasets_gen` and generate.py.

    python -m datasets_gen [SCENE.blend] --demo --out DIR [--train-views 100] [--val-views 100]
        [--test-views 200] [--resolution 800 | --width W --height H] [--samples 128] [--seed 0]
        [--sphere] [--device CPU] [--overwrite]

Bad input exits with status 2 and a single line on stderr naming the file or flag.
"""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn, Optional, Sequence

from .options import DEVICES, DatasetGenError, GeneratorOptions

PROG = "datasets_gen"
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


class _OneLineParser(argparse.ArgumentParser):
    """argparse that reports errors as one line (no usage dump), like the rest of the CLI."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog=PROG,
        description="Render a NeRF dataset (nerf_synthetic / Realistic Synthetic 360 protocol) "
        "from a .blend file or the built-in demo scene.",
    )
    parser.add_argument("scene", nargs="?", metavar="SCENE.blend", help="scene to render (or use --demo)")
    parser.add_argument("--demo", action="store_true", help="render the built-in procedural demo scene")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (must be empty or new)")
    parser.add_argument("--train-views", type=int, default=100, metavar="N", help="default: 100")
    parser.add_argument("--val-views", type=int, default=100, metavar="N", help="default: 100")
    parser.add_argument("--test-views", type=int, default=200, metavar="N",
                        help="default: 200 (the protocol's spiral; other counts keep its two turns)")
    parser.add_argument("--resolution", type=int, metavar="N", help="square image size (default: 800)")
    parser.add_argument("--width", type=int, metavar="W", help="image width (with --height)")
    parser.add_argument("--height", type=int, metavar="H", help="image height (with --width)")
    parser.add_argument("--samples", type=int, default=128, metavar="N", help="Cycles samples (default: 128)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random views and of Cycles (default: 0)")
    parser.add_argument("--sphere", action="store_true",
                        help="train/val views on the full sphere instead of the upper hemisphere")
    parser.add_argument("--device", default="CPU", choices=DEVICES, help="Cycles device (default: CPU)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the dataset in a non-empty --out folder")
    parser.add_argument("--no-progress", action="store_true", help="do not show progress on stderr")
    return parser


def options_from_args(args: argparse.Namespace, parser: argparse.ArgumentParser) -> GeneratorOptions:
    """Turn parsed arguments into validated GeneratorOptions (errors through `parser.error`)."""
    if args.resolution is not None and (args.width is not None or args.height is not None):
        parser.error("argument --resolution: not allowed with --width/--height")
    if (args.width is None) != (args.height is None):
        parser.error("arguments --width and --height must be given together")
    if args.resolution is not None:
        width = height = args.resolution
    elif args.width is not None:
        width, height = args.width, args.height
    else:
        width = height = 800
    options = GeneratorOptions(
        out_dir=args.out,
        demo=args.demo,
        blend_path=args.scene,
        train_views=args.train_views,
        val_views=args.val_views,
        test_views=args.test_views,
        width=width,
        height=height,
        samples=args.samples,
        seed=args.seed,
        full_sphere=args.sphere,
        device=args.device,
        overwrite=args.overwrite,
    )
    try:
        return options.validate()
    except DatasetGenError as error:
        parser.error(str(error))


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the CLI; return the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    options = options_from_args(args, parser)
    from .generator import run

    try:
        run(options, progress=not args.no_progress)
    except DatasetGenError as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; {options.out_dir} holds no complete dataset", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"{PROG}: wrote {options.out_dir}", file=sys.stderr)
    return 0
