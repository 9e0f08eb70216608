"""``compare --reference A --render B --out DIR``: score one render against one reference image
(PSNR, SSIM, LPIPS) and write their difference heatmap and the two side by side."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import COMPARE, BackendFlag
from nerf_contract.run_layout import COMPARE_NAME, DIFFERENCE_NAME

from ..core.devices import resolve_device
from ..evaluation.evaluate import compare_images
from ..metrics.registry import summary_line
from .arguments import add_device, add_lpips_weights

NAME = COMPARE
HELP = "score one render against one reference image (PSNR, SSIM, LPIPS) and write their difference heatmap"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(BackendFlag.REFERENCE, type=Path, required=True, help="e.g. the Cycles render")
    parser.add_argument(BackendFlag.RENDER, type=Path, required=True, help="e.g. the NeRF render of the same camera")
    parser.add_argument(BackendFlag.OUT, type=Path, required=True, help="folder for compare.json and difference.png")
    add_device(parser)
    add_lpips_weights(parser)


def run(args: argparse.Namespace) -> int:
    result = compare_images(args.reference, args.render, args.out, resolve_device(args.device), args.lpips_weights,
                            args.lpips_linear)
    print(f"{summary_line(result)}; written {args.out / COMPARE_NAME}, {args.out / DIFFERENCE_NAME}")
    return 0
