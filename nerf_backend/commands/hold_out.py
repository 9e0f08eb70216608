"""``hold-out SOURCE --out DATASET``: a dataset of train / val / test splits made from one split's
views by holding out every N-th view (nerf_synthetic's public training views of lego: views 0, 8,
... 96 test, 4 and 12 val, the other 85 train)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import BackendFlag

from ..data.hold_out import write_held_out_dataset
from .arguments import positive_int

NAME = "hold-out"
HELP = "split one split's views into train / val / test, every N-th view held out for testing"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", type=Path, help="a dataset folder (its transforms_train.json and images)")
    parser.add_argument(BackendFlag.OUT, type=Path, required=True, help="the new dataset's folder (must not exist)")
    parser.add_argument("--every", type=positive_int, default=8, help="hold out views 0, N, 2N, ... for testing")
    parser.add_argument("--val-views", type=int, default=2,
                        help="validation views, taken half-way between test views")
    parser.add_argument(BackendFlag.SPLIT, default="train", help="the source's split to divide")


def run(args: argparse.Namespace) -> int:
    counts = write_held_out_dataset(args.source, args.out, args.every, args.val_views, args.split)
    print(f"written {args.out}: " + ", ".join(f"{count} {name}" for name, count in counts.items()))
    return 0
