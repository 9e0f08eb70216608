"""``report RUN... [--out DIR]``: an HTML page comparing renders with Cycles ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import REPORT, BackendFlag

from ..evaluation.report import write_report

NAME = REPORT
HELP = "write an HTML page comparing renders with Cycles ground truth"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("results", type=Path, nargs="+",
                        help="run folders, or renders folders scored by eval --dataset D --renders DIR")
    parser.add_argument(BackendFlag.OUT, type=Path, default=None, help="default: FIRST/report")
    parser.add_argument(BackendFlag.SPLIT, default="test", help="the dataset split shown")


def run(args: argparse.Namespace) -> int:
    print(f"report: {write_report(args.results, args.out, split=args.split)}")
    return 0
