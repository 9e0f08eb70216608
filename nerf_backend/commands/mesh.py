"""``mesh RUN --out MESH.ply``: the trained density's surface as a coloured mesh (marching
cubes), in Blender's world coordinates."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_contract.commands import MESH, BackendFlag

from ..core.devices import resolve_device
from ..data.run_folder import RunFolder
from ..evaluation.mesh import mesh_run
from .arguments import add_device, positive_float, positive_int

NAME = MESH
HELP = "extract the trained density's surface as a mesh (marching cubes), coloured, in Blender's world coordinates"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="the run folder")
    parser.add_argument(BackendFlag.OUT, type=Path, required=True,
                        help="MESH.ply or MESH.obj (a record MESH.ply.json beside it)")
    parser.add_argument(BackendFlag.RESOLUTION, type=positive_int, default=256,
                        help="grid vertices along the scene box's longest side (default: 256)")
    parser.add_argument("--threshold", type=positive_float, default=None,
                        help="surface density (default: ln 2 / the render step, where one step is half opaque; "
                             "a surface run: its signed distance's zero level set, unless a threshold is given)")
    add_device(parser)
    parser.add_argument(BackendFlag.OVERWRITE, action="store_true", help="replace an existing mesh file")


def run(args: argparse.Namespace) -> int:
    record = mesh_run(RunFolder(args.run), args.out, resolve_device(args.device), args.resolution, args.threshold,
                      overwrite=args.overwrite)
    print(f"mesh: {record['vertices']} vertices, {record['faces']} faces at density {record['threshold']:.4g} "
          f"(iteration {record['iteration']}); written {args.out} and {args.out}.json")
    return 0
