"""``bench DATASET | --suite PATH... --out BENCH``: the speed/accuracy trade of presets, on one
dataset or on every dataset of a suite."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import BackendFlag

from ..bench import DEFAULT_PRESETS, Variant, ablation_variants, run_bench, run_suite, run_trade
from ..core.errors import NerfError
from .arguments import add_device, add_seed, positive_float, positive_int
from .page_option import add_page, publish

NAME = "bench"
HELP = "measure the speed/accuracy trade of presets on one dataset, or on every dataset of a suite (--suite)"


def positive_floats(text: str) -> tuple[float, ...]:
    """Comma-separated positive numbers: ``--budget-seconds``' budgets (each trained from
    scratch), ``--points``' points along one run."""
    return tuple(positive_float(part) for part in text.split(",") if part.strip())


def curve_points(text: str) -> int | tuple[float, ...]:
    """``--points``: a count, or the budgets themselves (``60,120,300``)."""
    return positive_int(text) if "," not in text else positive_floats(text)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, nargs="?", help="the dataset (or give --suite)")
    parser.add_argument("--suite", type=Path, nargs="+", default=None, metavar="PATH",
                        help="bench every dataset of these folders (each subfolder with a transforms_train.json; a "
                             "dataset folder counts as itself) into OUT/NAME, and write OUT/summary.{json,md,png}; "
                             "finished scenes are kept, unfinished ones benched again")
    parser.add_argument("--presets", default=None,
                        help="comma-separated presets or variants NAME=PRESET+KEY=VALUE+... "
                             "(default: preview,fast,auto,paper)")
    parser.add_argument("--ablations", nargs="?", const="paper", default=None, metavar="PRESET",
                        help="add the NeRF paper's ablations of a NeRF preset (default: paper): no PE, no view "
                             "dependence, no hierarchical sampling, 50 and 25 views, L = 5 and 15; and check their "
                             "order against the paper's")
    parser.add_argument("--budget-seconds", type=positive_floats, default=None,
                        help="training seconds per variant; several (60,120,300,600,1800) bench each budget from "
                             "scratch into OUT/<budget>s and write the trade across them into OUT/trade.{json,md,png}")
    parser.add_argument(BackendFlag.ITERATIONS, type=positive_int, default=None, help="or: iterations per variant")
    parser.add_argument("--points", type=curve_points, default=6,
                        help="evaluations along each curve: a count, spaced quadratically, or the budgets themselves "
                             "(seconds or iterations, comma-separated: 60,120,300,600); the last is always the whole "
                             "budget")
    parser.add_argument("--curve-views", type=positive_int, default=8, help="test views scored at each point")
    add_seed(parser)
    add_device(parser)
    parser.add_argument(BackendFlag.OUT, type=Path, required=True,
                        help="the bench folder (bench.json, bench.md, bench.png, runs/)")
    parser.add_argument(BackendFlag.OVERWRITE, action="store_true", help="bench again into an existing folder")
    add_page(parser)


def run(args: argparse.Namespace) -> int:
    names = (args.presets or ("" if args.ablations else DEFAULT_PRESETS)).split(",")
    names = [n for n in names if n] + (ablation_variants(args.ablations) if args.ablations else [])
    if (args.dataset is None) == (args.suite is None):
        raise NerfError("bench: give a DATASET or --suite PATH ... (not both)")
    variants = [Variant.parse(n) for n in names]
    common = dict(points=args.points, curve_views=args.curve_views, seed=args.seed, device=args.device,
                  overwrite=args.overwrite, command=args.command_line)
    seconds = args.budget_seconds or ()
    if len(seconds) > 1:
        if args.iters is not None:
            raise NerfError("bench: give either several --budget-seconds or --iters, not both")
        run_trade(args.suite or [args.dataset], variants, args.out, seconds, **common)
        name, also = "trade", f" and each budget's bench in {args.out}/<budget>s"
    elif args.suite is not None:
        run_suite(args.suite, variants, args.out, seconds[0] if seconds else None, args.iters, **common)
        name, also = "summary", f" and each scene's bench in {args.out}/NAME"
    else:
        run_bench(args.dataset, variants, args.out, seconds[0] if seconds else None, args.iters, **common)
        name, also = "bench", ""
    print((args.out / f"{name}.md").read_text(), end="")
    print(f"written {args.out / f'{name}.json'}, {args.out / f'{name}.md'}, {args.out / f'{name}.png'}{also}")
    publish(args, args.out / f"{name}.md", args.out / f"{name}.png")
    return 0
