"""``bench-view RUN --out DIR``: how fast the live view answers (``serve``, as the add-on runs
it): the server's start, frames a second while a camera orbits at a fraction of the size, the
whole frame after it rests (``bench/view_speed.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import BackendFlag

from ..bench.view_speed import view_speed
from ..core.devices import resolve_device
from ..core.errors import NerfError
from .arguments import add_device, positive_float, positive_int
from .page_option import add_page, publish

NAME = "bench-view"
HELP = "how fast the live view answers: the render server's start, frames a second while orbiting, the whole frame"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="the trained run")
    parser.add_argument("--size", type=positive_int, default=None,
                        help="the region's width in pixels (default: the dataset's; its height keeps the aspect)")
    parser.add_argument("--fraction", type=positive_float, default=0.25,
                        help="the orbit frames' size as a fraction of the region's side (the add-on's while moving)")
    parser.add_argument("--frames", type=positive_int, default=30, help="timed orbit frames")
    parser.add_argument("--beside-training", action="store_true",
                        help="time it while a real training runs on the run's dataset (all cores but one, as the "
                             "add-on trains)")
    add_device(parser)
    parser.add_argument(BackendFlag.OUT, type=Path, required=True, help="folder for the timings (JSON and Markdown)")
    add_page(parser)


def run(args: argparse.Namespace) -> int:
    if args.fraction > 1:
        raise NerfError("bench-view --fraction: at most 1 (the whole region)")
    view_speed(args.run, args.out, size=args.size, fraction=args.fraction, frames=args.frames,
               device=str(resolve_device(args.device)), beside_training=args.beside_training)
    print((args.out / "view_speed.md").read_text(), end="")
    publish(args, args.out / "view_speed.md")
    return 0
