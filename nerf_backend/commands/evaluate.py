"""``eval RUN | --dataset D --renders DIR``: score renders against the dataset's ground truth: a
run's (rendered first if needed) or any tool's; ``--geometry`` also measures the run's surface."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import BackendFlag
from nerf_contract.run_layout import METRICS_NAME

from ..core.devices import resolve_device
from ..core.errors import NerfError
from ..data.run_folder import RunFolder
from ..evaluation.evaluate import evaluate_renders, evaluate_run
from ..evaluation.geometry_eval import DEFAULT_RESOLUTION as DEFAULT_MESH_RESOLUTION
from ..evaluation.geometry_eval import GEOMETRY_NAME, GEOMETRY_PICTURE, geometry_line, score_geometry
from .arguments import add_device, add_lpips_weights, positive_float, positive_int

NAME = "eval"
HELP = ("score renders against the dataset's ground truth: a run's (rendered first if needed) or any tool's "
        "(--dataset D --renders DIR)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, nargs="?", help="a run folder (or give --dataset and --renders)")
    parser.add_argument("--dataset", type=Path, default=None, help="with --renders: the dataset they render")
    parser.add_argument("--renders", type=Path, default=None,
                        help="a folder of renders from any tool: STEM.png for each view of the split")
    parser.add_argument(BackendFlag.OUT, type=Path, default=None,
                        help="with --renders: where metrics.json goes (default: the renders folder)")
    parser.add_argument(BackendFlag.SPLIT, default="test", help="the dataset split scored")
    add_device(parser)
    parser.add_argument("--chunk", type=positive_int, default=None, help="rays per forward pass when rendering")
    parser.add_argument(BackendFlag.NO_PROGRESS, action="store_true", help="no progress bar")
    parser.add_argument("--geometry", action="store_true",
                        help="also measure the run's surface (its mesh) against the scene's true one (the "
                             "dataset's scene_geometry.ply): Chamfer, F-score at 1 %% of the bounding-sphere "
                             "radius, normal consistency; writes RUN/geometry.json and RUN/geometry.png")
    parser.add_argument("--mesh-resolution", type=positive_int, default=DEFAULT_MESH_RESOLUTION,
                        help=f"with --geometry: as mesh --resolution (default: {DEFAULT_MESH_RESOLUTION})")
    parser.add_argument("--mesh-threshold", type=positive_float, default=None,
                        help="with --geometry: as mesh --threshold (default: ln 2 / the render step; a surface "
                             "run: its signed distance's zero level set)")
    add_lpips_weights(parser)


def run(args: argparse.Namespace) -> int:
    if (args.run is None) == (args.renders is None and args.dataset is None):
        raise NerfError("eval: give a run folder, or --dataset and --renders (not both)")
    if args.geometry and args.run is None:
        raise NerfError("eval --geometry: give a run folder (its mesh is what is measured)")
    device = resolve_device(args.device)
    if args.geometry:  # first: a dataset without the true surface is refused before any rendering
        geometry = score_geometry(RunFolder(args.run), device, args.mesh_resolution, args.mesh_threshold)
        print(f"{geometry_line(geometry)}; written {args.run / GEOMETRY_NAME}, {args.run / GEOMETRY_PICTURE}")
    if args.run is not None:
        metrics = evaluate_run(args.run, args.split, device, args.lpips_weights, args.lpips_linear,
                               chunk=args.chunk, progress=not args.no_progress)
        written = args.run / METRICS_NAME
    else:
        if args.dataset is None or args.renders is None:
            raise NerfError("eval: --dataset and --renders go together")
        metrics = evaluate_renders(args.dataset, args.renders, args.split, device, args.out,
                                   args.lpips_weights, args.lpips_linear)
        written = (args.out or args.renders) / METRICS_NAME
    lpips = (f"LPIPS {metrics['lpips']:.4f}" if metrics["lpips"] is not None
             else f"LPIPS unavailable ({metrics['lpips_unavailable']})")
    depth = f", depth MAE {metrics['depth_mae']:.4f}" if metrics["depth_mae"] is not None else ""
    print(f"{args.split}: mean PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, {lpips}{depth} "
          f"over {metrics['views']} views; written {written}")
    return 0
