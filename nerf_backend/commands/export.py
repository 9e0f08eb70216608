"""``export RUN --out ASSET.glb``: the trained surface as a textured asset (decimated, UV-
unwrapped, the NeRF's colour baked into its texture), glTF binary, in Blender's world frame."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import EXPORT, BackendFlag

from ..asset.export import DEFAULT_TEXTURE_SIZE, DEFAULT_TRIANGLES, export_run
from ..core.devices import resolve_device
from ..data.run_folder import RunFolder
from .arguments import add_cpu_threads, add_device, positive_float, positive_int, use_cpu_threads

NAME = EXPORT
HELP = "bake the trained surface and its colour into a textured glTF asset (ASSET.glb) that Blender imports"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="the run folder")
    parser.add_argument(BackendFlag.OUT, type=Path, required=True, help="ASSET.glb (a record ASSET.glb.json beside it)")
    parser.add_argument(BackendFlag.TRIANGLES, type=positive_int, default=DEFAULT_TRIANGLES,
                        help="the most triangles the asset keeps (the surface is decimated to it)")
    parser.add_argument(BackendFlag.TEXTURE_SIZE, type=positive_int, default=DEFAULT_TEXTURE_SIZE,
                        help="texels along the square texture's side")
    parser.add_argument(BackendFlag.RESOLUTION, type=positive_int, default=256,
                        help="grid vertices along the scene box's longest side for the surface, before decimation")
    parser.add_argument("--threshold", type=positive_float, default=None,
                        help="surface density, as mesh --threshold takes it (default: mesh's rule)")
    add_device(parser)
    add_cpu_threads(parser)
    parser.add_argument(BackendFlag.NO_PROGRESS, action="store_true", help="no progress bar")
    parser.add_argument(BackendFlag.OVERWRITE, action="store_true", help="replace an existing asset")


def run(args: argparse.Namespace) -> int:
    use_cpu_threads(args)
    record = export_run(RunFolder(args.run), args.out, resolve_device(args.device), args.triangles,
                        args.texture_size, args.resolution, args.threshold, overwrite=args.overwrite,
                        progress=not args.no_progress)
    print(f"export: {record['triangles']} triangles, {args.texture_size}² texture, {record['bytes'] / 1e6:.1f} MB; "
          f"written {args.out} and {args.out}.json")
    return 0
