"""``bench-step DATASET --out DIR``: a NeRF preset's seconds per iteration against a plain
PyTorch implementation of the same maths; a marched preset's training step and rendered view
split by stage, against this machine's limits."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import BackendFlag

from ..bench import profile_marched_step, step_cost
from ..configs.presets import preset_config
from ..core.errors import NerfError
from ..models.marched import MarchedModel
from ..models.registry import model_class
from .arguments import add_device, add_seed, positive_float, positive_int
from .page_option import add_page, publish

NAME = "bench-step"
HELP = ("a NeRF preset's seconds per iteration against a plain PyTorch implementation of the same maths; a "
        "marched preset's training step and rendered view split by stage, against this machine's limits")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", type=Path, help="the dataset folder")
    parser.add_argument(BackendFlag.PRESET, default="paper", help="the preset to time")
    parser.add_argument("--steps", type=positive_int, default=None,
                        help="timed iterations (default: 3 for NeRF presets; for marched ones the fewest whole periods of "
                             "the occupancy grid's refresh that make at least 50)")
    parser.add_argument("--rays", type=positive_int, default=None, help="rays per batch (default: the preset's)")
    parser.add_argument("--warmup-seconds", type=positive_float, default=60.0,
                        help="marched presets: training before the timed steps, the whole schedule laid over it")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="marched presets: change a setting of the preset")
    parser.add_argument("--from-run", type=Path, default=None, metavar="RUN",
                        help="marched presets: no warm-up; time steps continuing a copy of this trained run (its "
                             "preset), so that two versions of the code time the same state")
    parser.add_argument("--before", type=Path, default=None, metavar="STEP_PROFILE_JSON",
                        help="marched presets: an earlier step_profile.json to show beside this one, stage by stage")
    add_device(parser)
    add_seed(parser)
    parser.add_argument(BackendFlag.OUT, type=Path, required=True, help="folder for the timings (JSON and Markdown)")
    parser.add_argument(BackendFlag.OVERWRITE, action="store_true", help="replace an existing output folder")
    add_page(parser)


def run(args: argparse.Namespace) -> int:
    if args.from_run is not None or issubclass(model_class(preset_config(args.preset).model), MarchedModel):
        return _profile_marched(args)
    if args.before is not None:
        raise NerfError("bench-step --before: a marched preset's profile is compared by stage; a NeRF preset's is not")
    if args.overrides:
        raise NerfError("bench-step: --set applies to marched presets; a NeRF preset is measured as it is")
    if args.page is not None:
        raise NerfError("bench-step --page: a marched preset's profile is a page; a NeRF preset's timing is not")
    report = step_cost(args.dataset, args.preset, args.steps or 3, args.out, seed=args.seed, rays=args.rays,
                       overwrite=args.overwrite)
    per = report["seconds_per_iteration"]
    print(f"{args.preset}, {report['rays_per_batch']} rays: this project {per['project']:.2f} s/iteration, "
          f"plain PyTorch {per['plain']:.2f} s/iteration (ratio {report['ratio_project_to_plain']:.2f}; "
          f"{report['parameters']['project']:,} vs {report['parameters']['plain']:,} parameters); "
          f"written {args.out / 'step_cost.json'}")
    return 0


def _profile_marched(args: argparse.Namespace) -> int:
    overrides = tuple(args.overrides) + ((f"rays_per_batch={args.rays}",) if args.rays else ())
    if args.from_run is not None and overrides:
        raise NerfError("bench-step --from-run: the run's own settings are timed; --set and --rays apply to a new "
                        "warm-up")
    profile_marched_step(args.dataset, args.preset, args.steps, args.out, seed=args.seed,
                         warmup_seconds=args.warmup_seconds, overrides=overrides, device_name=args.device,
                         overwrite=args.overwrite, from_run=args.from_run, before=args.before)
    print((args.out / "step_profile.md").read_text(), end="")
    publish(args, args.out / "step_profile.md")
    print(f"written {args.out / 'step_profile.json'}, {args.out / 'step_profile.md'}")
    return 0
