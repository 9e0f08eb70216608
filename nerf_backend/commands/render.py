"""``render RUN``: render with a trained run, in one of three modes, chosen by the flags:

- a split's views (the default; ``--split``, ``--scale``) into ``RUN/renders/SPLIT``;
- ``--cameras CAMERAS.json --out DIR``: the cameras of a transforms JSON (no images needed);
- ``--camera-path PATH.json [--out DIR] [--cycles]``: a camera animation, a PNG per frame and an
  MP4, with ``--cycles`` beside the path's Cycles frames (side-by-side video, metrics per frame).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from nerf_contract.commands import RENDER, BackendFlag
from nerf_contract.run_layout import RENDERS_DIR

from ..core.cpu_steal import steal_note
from ..core.devices import resolve_device
from ..core.errors import NerfError
from ..data.run_folder import RunFolder
from ..evaluation.animation import FRAME_METRICS, render_animation
from ..evaluation.inference import RENDERS_RECORD, render_cameras, render_split
from ..metrics.registry import summary_line
from ..model_components.compiled_march import RENDER_CHUNK as COMPILED_RENDER_CHUNK
from ..models.base import Model
from ..models.marched import MarchedModel
from .arguments import add_device, positive_float, positive_int

NAME = RENDER
HELP = "render a split's views with a trained run (or cameras, or a camera animation)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="the run folder")
    parser.add_argument(BackendFlag.SPLIT, default="test", help="the dataset split whose views are rendered")
    add_device(parser)
    parser.add_argument("--chunk", type=positive_int, default=None,
                        help=f"rays per forward pass; bounds memory (default: the model's, {Model.render_chunk} "
                             f"for NeRF MLPs, {MarchedModel.TORCH_RENDER_CHUNK} for marched models, "
                             f"{COMPILED_RENDER_CHUNK} where the compiled CPU march renders)")
    parser.add_argument(BackendFlag.CAMERAS, type=Path, default=None,
                        help="render these cameras instead (a transforms JSON with w, h and intrinsics; no images)")
    parser.add_argument(BackendFlag.CAMERA_PATH, type=Path, default=None, metavar="PATH.json",
                        help="render a camera animation instead (camera_path.json from datasets_gen --camera-path or "
                             "the add-on): a PNG per frame and an MP4 at the scene's frame rate, into --out "
                             "(default: RUN/animation/CAMERA); frames already rendered are kept")
    parser.add_argument(BackendFlag.CYCLES, action="store_true",
                        help="with --camera-path: compare with the path's Cycles frames: a side-by-side video "
                             "(Cycles | NeRF | error), PSNR/SSIM per frame (JSON and plot)")
    parser.add_argument(BackendFlag.OUT, type=Path, default=None,
                        help="with --cameras or --camera-path: the output folder")
    parser.add_argument("--scale", type=positive_float, default=1.0,
                        help=f"render at this multiple of the dataset's resolution (into {RENDERS_DIR}/SPLIT_xSCALE)")
    parser.add_argument(BackendFlag.NO_PROGRESS, action="store_true", help="no progress bar")


def mode(args: argparse.Namespace) -> str:
    """Which of the three renders the flags ask for; NerfError for flags that do not go together."""
    if args.camera_path is not None and args.cameras is not None:
        raise NerfError("render: give --cameras or --camera-path, not both")
    if args.cycles and args.camera_path is None:
        raise NerfError("render --cycles: needs --camera-path")
    if args.camera_path is not None:
        return "camera_path"
    if args.cameras is not None:
        if args.out is None:
            raise NerfError("render --cameras: give --out, the folder for the images")
        return "cameras"
    return "split"


def run(args: argparse.Namespace) -> int:
    return MODES[mode(args)](args)


def _camera_path(args: argparse.Namespace) -> int:
    record = render_animation(RunFolder(args.run), args.camera_path, resolve_device(args.device), args.out,
                              chunk=args.chunk, cycles=args.cycles, progress=not args.no_progress)
    width, height = record["size"]
    speed = (f"{record['seconds_per_frame']:.2f} s per frame on {record['device']}"
             if record["seconds_per_frame"] is not None else "every frame was already rendered")
    compared = ""
    if args.cycles:
        compared = (f"; against Cycles: {summary_line(record['mean'], FRAME_METRICS)} (mean of "
                    f"{len(record['frames'])} frames); written {record['side_by_side_video']}")
    print(f"rendered {len(record['frames'])} frames at {width}×{height} ({speed}): {record['video']}{compared}")
    return 0


def _cameras(args: argparse.Namespace) -> int:
    paths = render_cameras(RunFolder(args.run), args.cameras, args.out, resolve_device(args.device), chunk=args.chunk)
    print(f"rendered {len(paths)} views into {args.out}")
    return 0


def _split(args: argparse.Namespace) -> int:
    out = render_split(RunFolder(args.run), args.split, resolve_device(args.device), chunk=args.chunk,
                       progress=not args.no_progress, scale=args.scale)
    record = json.loads((out / RENDERS_RECORD).read_text())
    width, height = record["size"]
    note = steal_note(record.get("cpu_stolen_share"))
    print(f"rendered {len(record['views'])} {args.split} views at {width}×{height} into {out}: "
          f"{record['seconds_per_view']:.2f} s per view on {record['device']}" + (f". {note}" if note else ""))
    return 0


MODES = {"camera_path": _camera_path, "cameras": _cameras, "split": _split}
