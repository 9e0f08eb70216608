"""``bench-kilonerf RUN --out DIR``: KiloNeRF measured for the live view: the run distilled into
a grid of tiny networks, then both rendered through the same march, PSNR and time a frame at
the full size and a quarter (``bench/kilonerf.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import BackendFlag

from ..bench.kilonerf import kilonerf_trade
from ..core.devices import resolve_device
from .arguments import add_device, positive_float, positive_int
from .page_option import add_page, publish

NAME = "bench-kilonerf"
HELP = "KiloNeRF against the product's renderer: the run distilled into tiny networks, PSNR and time a frame"


def _cells(text: str) -> tuple[int, int, int]:
    parts = text.split(",")
    if len(parts) != 3 or not all(part.strip().isdigit() and int(part) > 0 for part in parts):
        raise argparse.ArgumentTypeError(f"{text!r}: three positive whole numbers, e.g. 9,16,10")
    return tuple(int(part) for part in parts)  # type: ignore[return-value]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="the trained run (a marched model: auto, fast, plenoxels, hash)")
    parser.add_argument("--seconds", type=positive_float, default=300.0, help="distillation time")
    parser.add_argument("--cells", type=_cells, default=None,
                        help="cells per axis, X,Y,Z (default: 16 along the box's longest side, the others in proportion)")
    parser.add_argument("--views", type=positive_int, default=3, help="test views scored (the dataset's first)")
    add_device(parser)
    parser.add_argument(BackendFlag.OUT, type=Path, required=True, help="folder for the figures (JSON and Markdown)")
    add_page(parser)


def run(args: argparse.Namespace) -> int:
    kilonerf_trade(args.run, args.out, args.seconds, cells=args.cells, views=args.views,
                   device=str(resolve_device(args.device)))
    print((args.out / "kilonerf.md").read_text(), end="")
    publish(args, args.out / "kilonerf.md")
    return 0
