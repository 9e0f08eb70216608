"""``train DATASET --out RUN``: train a NeRF on a dataset in the nerf_synthetic layout."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nerf_contract.commands import TRAIN, BackendFlag
from nerf_contract.run_layout import EVENTS_NAME

from ..configs.presets import DEFAULT_PRESET, PRESETS
from ..training.trainer import TrainOptions, train
from .arguments import add_cpu_threads, add_device, add_seed, positive_float, positive_int, use_cpu_threads

NAME = TRAIN
HELP = "train a NeRF on a dataset in the nerf_synthetic layout"
# The exit status when the run ended on a model collapsed to the blank image (bad input: 2).
EXIT_COLLAPSED = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="the dataset folder (transforms_train.json and its images)")
    parser.add_argument(BackendFlag.PRESET, choices=sorted(PRESETS), default=None,
                        help=f"model/sampling/optimiser preset (default: {DEFAULT_PRESET}; on --resume: the run's)")
    parser.add_argument(BackendFlag.OUT, type=Path, required=True, help="the run folder")
    parser.add_argument(BackendFlag.ITERATIONS, type=positive_int, default=None,
                        help="total iterations for the run (default: the preset's, or with --max-seconds alone, "
                             "as many as the time allows)")
    parser.add_argument(BackendFlag.MAX_SECONDS, type=positive_float, default=None,
                        help="total training seconds for the run; the schedule is laid over them (default: no limit)")
    add_seed(parser)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                        help="change one preset setting, e.g. grid.resolution=96 (repeatable)")
    add_device(parser)
    parser.add_argument(BackendFlag.RESUME, action="store_true", help="continue the run in --out from its checkpoint")
    parser.add_argument(BackendFlag.OVERWRITE, action="store_true", help="replace an existing run folder")
    parser.add_argument(BackendFlag.NO_PROGRESS, action="store_true", help="no progress bar")
    add_cpu_threads(parser)


def run(args: argparse.Namespace) -> int:
    use_cpu_threads(args)
    summary = train(TrainOptions(
        dataset=args.dataset, run=args.out, preset=args.preset, iterations=args.iters,
        max_seconds=args.max_seconds, seed=args.seed, overrides=tuple(args.overrides), device=args.device,
        resume=args.resume, overwrite=args.overwrite, progress=not args.no_progress,
    ))
    val = f", validation PSNR {summary.val_psnr:.2f} dB" if summary.val_psnr is not None else ""
    if summary.had_nothing_to_do:
        limit = "time budget" if summary.stop_reason == "time" else "iteration count"
        print(f"nothing to do: the run had already reached its {limit} "
              f"({summary.iteration} iterations, {summary.train_seconds:.1f} s); raise --iters or "
              f"--max-seconds to train on{val}; run: {args.out}")
        return 0
    rate = f", {summary.throughput_words()}" if summary.throughput_words() else ""
    print(f"trained {summary.iteration} iterations in {summary.train_seconds:.1f} s{rate} "
          f"(stopped: {summary.stop_reason}){val}; run: {args.out}")
    if summary.collapse is not None:
        print(f"error: training failed: the model collapsed to the blank image "
              f"({summary.collapse.describe()}); see {args.out / EVENTS_NAME}", file=sys.stderr)
        return EXIT_COLLAPSED
    return 0
