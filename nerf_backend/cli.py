"""``python -m nerf_backend {train,render,eval,compare,mesh,report,bench,bench-step}``."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import torch

from .bench import DEFAULT_PRESETS, Variant, ablation_variants, profile_marched_step, run_bench, run_suite, step_cost
from .configs.presets import DEFAULT_PRESET, PRESETS, preset_config
from .core.devices import resolve_device
from .core.errors import NerfError
from .data.run_folder import RunFolder
from .evaluation.animation import FRAME_METRICS, render_animation
from .evaluation.evaluate import compare_images, evaluate_renders, evaluate_run
from .evaluation.geometry_eval import DEFAULT_RESOLUTION as DEFAULT_MESH_RESOLUTION
from .evaluation.geometry_eval import geometry_line, score_geometry
from .evaluation.inference import render_cameras, render_split
from .evaluation.mesh import mesh_run
from .evaluation.report import write_report
from .metrics.lpips_metric import BACKBONE_FILE
from .metrics.registry import summary_line
from .models.base import Model
from .models.marched import MarchedModel
from .models.registry import model_class
from .training.trainer import TrainOptions, train

# `train`'s exit status when the run ended on a model collapsed to the blank image (bad input: 2).
EXIT_COLLAPSED = 3


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive whole number, got {text}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _curve_points(text: str) -> int | tuple[float, ...]:
    """``--points``: a count, or the budgets themselves (``60,120,300``)."""
    if "," not in text:
        return _positive_int(text)
    return tuple(_positive_float(part) for part in text.split(",") if part.strip())


class _DefaultsShown(argparse.HelpFormatter):
    """Every option's help ends with its default, unless it says it already or has none."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or not action.option_strings or action.default in (None, False, [], argparse.SUPPRESS):
            return text
        return f"{text} (default: %(default)s)"


DEVICE_HELP = "where to compute: auto takes CUDA, then Apple's MPS, then the CPU"
SEED_HELP = "seed of the model's initialisation and of the rays sampled"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m nerf_backend", description="Train, render, score and benchmark NeRFs of Blender scenes.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    sub = parser.add_subparsers(dest="command", required=True)

    train = sub.add_parser("train", help="train a NeRF on a dataset in the nerf_synthetic layout")
    train.add_argument("dataset", type=Path, help="the dataset folder (transforms_train.json and its images)")
    train.add_argument("--preset", choices=sorted(PRESETS), default=None,
                       help=f"model/sampling/optimiser preset (default: {DEFAULT_PRESET}; on --resume: the run's)")
    train.add_argument("--out", type=Path, required=True, help="the run folder")
    train.add_argument("--iters", type=_positive_int, default=None,
                       help="total iterations for the run (default: the preset's, or with --max-seconds alone, "
                            "as many as the time allows)")
    train.add_argument("--max-seconds", type=_positive_float, default=None,
                       help="total training seconds for the run; the schedule is laid over them (default: no limit)")
    train.add_argument("--seed", type=int, default=0, help=SEED_HELP)
    train.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                       help="change one preset setting, e.g. grid.resolution=96 (repeatable)")
    train.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda", "mps"], help=DEVICE_HELP)
    train.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    train.add_argument("--overwrite", action="store_true", help="replace an existing run folder")
    train.add_argument("--no-progress", action="store_true", help="no progress bar")
    train.add_argument("--cpu-threads", type=_positive_int, default=None, metavar="N",
                       help="threads for work on the CPU (default: one per core); the add-on leaves Blender a core, "
                            "since torch slows about 3x when another program takes one of the cores it uses")

    bench = sub.add_parser("bench", help="measure the speed/accuracy trade of presets on one dataset, or on "
                                         "every dataset of a suite (--suite)")
    bench.add_argument("dataset", type=Path, nargs="?", help="the dataset (or give --suite)")
    bench.add_argument("--suite", type=Path, nargs="+", default=None, metavar="PATH",
                       help="bench every dataset of these folders (each subfolder with a transforms_train.json; a "
                            "dataset folder counts as itself) into OUT/NAME, and write OUT/summary.{json,md,png}; "
                            "finished scenes are kept, unfinished ones benched again")
    bench.add_argument("--presets", default=None,
                       help="comma-separated presets or variants NAME=PRESET+KEY=VALUE+... "
                            "(default: preview,fast,auto,paper)")
    bench.add_argument("--ablations", nargs="?", const="paper", default=None, metavar="PRESET",
                       help="add the NeRF paper's ablations of a NeRF preset (default: paper): no PE, no view "
                            "dependence, no hierarchical sampling, 50 and 25 views, L = 5 and 15; and check their "
                            "order against the paper's")
    bench.add_argument("--budget-seconds", type=_positive_float, default=None, help="training seconds per variant")
    bench.add_argument("--iters", type=_positive_int, default=None, help="or: iterations per variant")
    bench.add_argument("--points", type=_curve_points, default=6,
                       help="evaluations along each curve: a count, spaced quadratically, or the budgets themselves "
                            "(seconds or iterations, comma-separated: 60,120,300,600); the last is always the whole "
                            "budget")
    bench.add_argument("--curve-views", type=_positive_int, default=8, help="test views scored at each point")
    bench.add_argument("--seed", type=int, default=0, help=SEED_HELP)
    bench.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda", "mps"], help=DEVICE_HELP)
    bench.add_argument("--out", type=Path, required=True, help="the bench folder (bench.json, bench.md, bench.png, runs/)")
    bench.add_argument("--overwrite", action="store_true", help="bench again into an existing folder")

    step = sub.add_parser("bench-step", help="a NeRF preset's seconds per iteration against a plain PyTorch "
                                             "implementation of the same maths; a marched preset's training step "
                                             "and rendered view split by stage, against this machine's limits")
    step.add_argument("dataset", type=Path, help="the dataset folder")
    step.add_argument("--preset", default="paper", help="the preset to time")
    step.add_argument("--steps", type=_positive_int, default=None,
                      help="timed iterations (default: 3 for NeRF presets, 50 for marched ones)")
    step.add_argument("--rays", type=_positive_int, default=None, help="rays per batch (default: the preset's)")
    step.add_argument("--warmup-seconds", type=_positive_float, default=60.0,
                      help="marched presets: training before the timed steps, the whole schedule laid over it")
    step.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                      help="marched presets: change a setting of the preset")
    step.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda", "mps"], help=DEVICE_HELP)
    step.add_argument("--seed", type=int, default=0, help=SEED_HELP)
    step.add_argument("--out", type=Path, required=True, help="folder for the timings (JSON and Markdown)")
    step.add_argument("--overwrite", action="store_true", help="replace an existing output folder")

    render = sub.add_parser("render", help="render a split's views with a trained run")
    render.add_argument("run", type=Path, help="the run folder")
    render.add_argument("--split", default="test", help="the dataset split whose views are rendered")
    render.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda", "mps"], help=DEVICE_HELP)
    render.add_argument("--chunk", type=_positive_int, default=None,
                        help=f"rays per forward pass; bounds memory (default: the model's, {Model.render_chunk} "
                             f"for NeRF MLPs, {MarchedModel.render_chunk} for marched models)")
    render.add_argument("--cameras", type=Path, default=None,
                        help="render these cameras instead (a transforms JSON with w, h and intrinsics; no images)")
    render.add_argument("--camera-path", type=Path, default=None, metavar="PATH.json",
                        help="render a camera animation instead (camera_path.json from datasets_gen --camera-path or "
                             "the add-on): a PNG per frame and an MP4 at the scene's frame rate, into --out "
                             "(default: RUN/animation/CAMERA); frames already rendered are kept")
    render.add_argument("--cycles", action="store_true",
                        help="with --camera-path: compare with the path's Cycles frames: a side-by-side video "
                             "(Cycles | NeRF | error), PSNR/SSIM per frame (JSON and plot)")
    render.add_argument("--out", type=Path, default=None, help="with --cameras or --camera-path: the output folder")
    render.add_argument("--scale", type=_positive_float, default=1.0,
                        help="render at this multiple of the dataset's resolution (into renders/SPLIT_xSCALE)")
    render.add_argument("--no-progress", action="store_true", help="no progress bar")

    evaluate = sub.add_parser("eval", help="score renders against the dataset's ground truth: a run's (rendered "
                                           "first if needed) or any tool's (--dataset D --renders DIR)")
    evaluate.add_argument("run", type=Path, nargs="?", help="a run folder (or give --dataset and --renders)")
    evaluate.add_argument("--dataset", type=Path, default=None, help="with --renders: the dataset they render")
    evaluate.add_argument("--renders", type=Path, default=None,
                          help="a folder of renders from any tool: STEM.png for each view of the split")
    evaluate.add_argument("--out", type=Path, default=None,
                          help="with --renders: where metrics.json goes (default: the renders folder)")
    evaluate.add_argument("--split", default="test", help="the dataset split scored")
    evaluate.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda", "mps"], help=DEVICE_HELP)
    evaluate.add_argument("--chunk", type=_positive_int, default=None, help="rays per forward pass when rendering")
    evaluate.add_argument("--no-progress", action="store_true", help="no progress bar")
    evaluate.add_argument("--geometry", action="store_true",
                          help="also measure the run's surface (its mesh) against the scene's true one (the "
                               "dataset's scene_geometry.ply): Chamfer, F-score at 1 %% of the bounding-sphere "
                               "radius, normal consistency; writes RUN/geometry.json and RUN/geometry.png")
    evaluate.add_argument("--mesh-resolution", type=_positive_int, default=DEFAULT_MESH_RESOLUTION,
                          help=f"with --geometry: as mesh --resolution (default: {DEFAULT_MESH_RESOLUTION})")
    evaluate.add_argument("--mesh-threshold", type=_positive_float, default=None,
                          help="with --geometry: as mesh --threshold (default: ln 2 / the render step)")

    compare = sub.add_parser("compare", help="score one render against one reference image (PSNR, SSIM, LPIPS) "
                                            "and write their difference heatmap")
    compare.add_argument("--reference", type=Path, required=True, help="e.g. the Cycles render")
    compare.add_argument("--render", type=Path, required=True, help="e.g. the NeRF render of the same camera")
    compare.add_argument("--out", type=Path, required=True, help="folder for compare.json and difference.png")
    compare.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda", "mps"], help=DEVICE_HELP)
    for command in (evaluate, compare):
        command.add_argument("--lpips-weights", type=Path, default=None,
                             help=f"torchvision's AlexNet weights ({BACKBONE_FILE}) for LPIPS (default: torch "
                                  "hub's cache, downloaded there on first use)")
        command.add_argument("--lpips-linear", type=Path, default=None,
                             help="LPIPS v0.1 linear-layer weights (default: the ones in the lpips package)")

    mesh = sub.add_parser("mesh", help="extract the trained density's surface as a mesh (marching cubes), "
                                       "coloured, in Blender's world coordinates")
    mesh.add_argument("run", type=Path, help="the run folder")
    mesh.add_argument("--out", type=Path, required=True, help="MESH.ply or MESH.obj (a record MESH.ply.json beside it)")
    mesh.add_argument("--resolution", type=_positive_int, default=256,
                      help="grid vertices along the scene box's longest side (default: 256)")
    mesh.add_argument("--threshold", type=_positive_float, default=None,
                      help="surface density (default: ln 2 / the render step, where one step is half opaque)")
    mesh.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda", "mps"], help=DEVICE_HELP)
    mesh.add_argument("--overwrite", action="store_true", help="replace an existing mesh file")

    report = sub.add_parser("report", help="write an HTML page comparing renders with Cycles ground truth")
    report.add_argument("results", type=Path, nargs="+",
                        help="run folders, or renders folders scored by eval --dataset D --renders DIR")
    report.add_argument("--out", type=Path, default=None, help="default: FIRST/report")
    report.add_argument("--split", default="test", help="the dataset split shown")
    for command in sub.choices.values():
        command.formatter_class = _DefaultsShown
    return parser


def _run(args: argparse.Namespace) -> int:
    if args.command == "train":
        if args.cpu_threads is not None:
            torch.set_num_threads(args.cpu_threads)
        summary = train(TrainOptions(
            dataset=args.dataset, run=args.out, preset=args.preset, iterations=args.iters,
            max_seconds=args.max_seconds, seed=args.seed, overrides=tuple(args.overrides), device=args.device, resume=args.resume,
            overwrite=args.overwrite, progress=not args.no_progress,
        ))
        val = f", validation PSNR {summary.val_psnr:.2f} dB" if summary.val_psnr is not None else ""
        if summary.had_nothing_to_do:
            limit = "time budget" if summary.stop_reason == "time" else "iteration count"
            print(f"nothing to do: the run had already reached its {limit} "
                  f"({summary.iteration} iterations, {summary.train_seconds:.1f} s); raise --iters or "
                  f"--max-seconds to train on{val}; run: {args.out}")
            return 0
        print(f"trained {summary.iteration} iterations in {summary.train_seconds:.1f} s "
              f"(stopped: {summary.stop_reason}){val}; run: {args.out}")
        if summary.collapse is not None:
            print(f"error: training failed: the model collapsed to the blank image "
                  f"({summary.collapse.describe()}); see {args.out / 'events.jsonl'}", file=sys.stderr)
            return EXIT_COLLAPSED
        return 0

    if args.command == "bench":
        names = (args.presets or ("" if args.ablations else DEFAULT_PRESETS)).split(",")
        names = [n for n in names if n] + (ablation_variants(args.ablations) if args.ablations else [])
        if (args.dataset is None) == (args.suite is None):
            raise NerfError("bench: give a DATASET or --suite PATH ... (not both)")
        if args.suite is not None:
            run_suite(args.suite, [Variant.parse(n) for n in names], args.out, args.budget_seconds, args.iters,
                      points=args.points, curve_views=args.curve_views, seed=args.seed, device=args.device,
                      overwrite=args.overwrite, command=args.command_line)
            print((args.out / "summary.md").read_text(), end="")
            print(f"written {args.out / 'summary.json'}, {args.out / 'summary.md'}, {args.out / 'summary.png'} "
                  f"and each scene's bench in {args.out}/NAME")
            return 0
        report = run_bench(args.dataset, [Variant.parse(n) for n in names], args.out, args.budget_seconds,
                           args.iters, points=args.points, curve_views=args.curve_views, seed=args.seed,
                           device=args.device, overwrite=args.overwrite, command=args.command_line)
        print((args.out / "bench.md").read_text(), end="")
        print(f"written {args.out / 'bench.json'}, {args.out / 'bench.md'}, {args.out / 'bench.png'}")
        return 0

    if args.command == "bench-step" and issubclass(model_class(preset_config(args.preset).model), MarchedModel):
        overrides = tuple(args.overrides) + ((f"rays_per_batch={args.rays}",) if args.rays else ())
        report = profile_marched_step(args.dataset, args.preset, args.steps or 50, args.out, seed=args.seed,
                                      warmup_seconds=args.warmup_seconds, overrides=overrides,
                                      device_name=args.device, overwrite=args.overwrite)
        print((args.out / "step_profile.md").read_text(), end="")
        print(f"written {args.out / 'step_profile.json'}, {args.out / 'step_profile.md'}")
        return 0

    if args.command == "bench-step":
        if args.overrides:
            raise NerfError("bench-step: --set applies to marched presets; a NeRF preset is measured as it is")
        report = step_cost(args.dataset, args.preset, args.steps or 3, args.out, seed=args.seed, rays=args.rays,
                           overwrite=args.overwrite)
        per = report["seconds_per_iteration"]
        print(f"{args.preset}, {report['rays_per_batch']} rays: this project {per['project']:.2f} s/iteration, "
              f"plain PyTorch {per['plain']:.2f} s/iteration (ratio {report['ratio_project_to_plain']:.2f}; "
              f"{report['parameters']['project']:,} vs {report['parameters']['plain']:,} parameters); "
              f"written {args.out / 'step_cost.json'}")
        return 0

    if args.command == "mesh":
        record = mesh_run(RunFolder(args.run), args.out, resolve_device(args.device), args.resolution,
                          args.threshold, overwrite=args.overwrite)
        print(f"mesh: {record['vertices']} vertices, {record['faces']} faces at density {record['threshold']:.4g} "
              f"(iteration {record['iteration']}); written {args.out} and {args.out}.json")
        return 0

    if args.command == "report":
        page = write_report(args.results, args.out, split=args.split)
        print(f"report: {page}")
        return 0

    device = resolve_device(args.device)
    if args.command == "compare":
        result = compare_images(args.reference, args.render, args.out, device, args.lpips_weights, args.lpips_linear)
        print(f"{summary_line(result)}; "
              f"written {args.out / 'compare.json'}, {args.out / 'difference.png'}")
        return 0
    if args.command == "render" and args.camera_path is not None:
        if args.cameras is not None:
            raise NerfError("render: give --cameras or --camera-path, not both")
        record = render_animation(RunFolder(args.run), args.camera_path, device, args.out, chunk=args.chunk,
                                  cycles=args.cycles, progress=not args.no_progress)
        width, height = record["size"]
        speed = (f"{record['seconds_per_frame']:.2f} s per frame on {record['device']}"
                 if record["seconds_per_frame"] is not None else "every frame was already rendered")
        compared = ""
        if args.cycles:
            compared = (f"; against Cycles: {summary_line(record['mean'], FRAME_METRICS)} (mean of "
                        f"{len(record['frames'])} frames); written {record['side_by_side_video']}")
        print(f"rendered {len(record['frames'])} frames at {width}×{height} ({speed}): {record['video']}{compared}")
        return 0
    if args.command == "render" and args.cycles:
        raise NerfError("render --cycles: needs --camera-path")
    if args.command == "render" and args.cameras is not None:
        if args.out is None:
            raise NerfError("render --cameras: give --out, the folder for the images")
        paths = render_cameras(RunFolder(args.run), args.cameras, args.out, device, chunk=args.chunk)
        print(f"rendered {len(paths)} views into {args.out}")
        return 0
    if args.command == "render":
        out = render_split(RunFolder(args.run), args.split, device, chunk=args.chunk, progress=not args.no_progress,
                           scale=args.scale)
        record = json.loads((out / "renders.json").read_text())
        width, height = record["size"]
        print(f"rendered {len(record['views'])} {args.split} views at {width}×{height} into {out}: "
              f"{record['seconds_per_view']:.2f} s per view on {record['device']}")
        return 0

    if (args.run is None) == (args.renders is None and args.dataset is None):
        raise NerfError("eval: give a run folder, or --dataset and --renders (not both)")
    if args.geometry and args.run is None:
        raise NerfError("eval --geometry: give a run folder (its mesh is what is measured)")
    if args.geometry:  # first: a dataset without the true surface is refused before any rendering
        geometry = score_geometry(RunFolder(args.run), device, args.mesh_resolution, args.mesh_threshold)
        print(f"{geometry_line(geometry)}; written {args.run / 'geometry.json'}, {args.run / 'geometry.png'}")
    if args.run is not None:
        metrics = evaluate_run(args.run, args.split, device, args.lpips_weights, args.lpips_linear,
                               chunk=args.chunk, progress=not args.no_progress)
        written = args.run / "metrics.json"
    else:
        if args.dataset is None or args.renders is None:
            raise NerfError("eval: --dataset and --renders go together")
        metrics = evaluate_renders(args.dataset, args.renders, args.split, device, args.out,
                                   args.lpips_weights, args.lpips_linear)
        written = (args.out or args.renders) / "metrics.json"
    lpips = (f"LPIPS {metrics['lpips']:.4f}" if metrics["lpips"] is not None
             else f"LPIPS unavailable ({metrics['lpips_unavailable']})")
    depth = f", depth MAE {metrics['depth_mae']:.4f}" if metrics["depth_mae"] is not None else ""
    print(f"{args.split}: mean PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, {lpips}{depth} "
          f"over {metrics['views']} views; written {written}")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    # Recorded in the bench's tables with the commit, so a figure can be made again.
    args.command_line = shlex.join(["python", "-m", "nerf_backend", *argv])
    try:
        return _run(args)
    except (NerfError, OSError) as exc:
        # One line naming the file and what is wrong; the traceback only with --debug.
        if args.debug:
            raise
        if isinstance(exc, NerfError):
            message = str(exc)
        elif exc.filename is not None:  # a full disk, permission denied, a file too large...: "FILE: strerror"
            names = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
            message = f"{names}: {exc.strerror or exc}"
        else:
            message = exc.strerror or str(exc) or type(exc).__name__
        # A name from a dataset may hold a newline: escaped, so the error stays one line.
        message = message.replace("\r", "\\r").replace("\n", "\\n")
        print(f"error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
