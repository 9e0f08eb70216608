"""``serve RUN --frames DIR``: keep the run's model loaded and render the views asked for on
stdin into frame files in ``DIR``, for the add-on's live view (``nerf_contract.view_frames``:
the requests, events and files; ``evaluation/view_server.py``: the server)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nerf_contract.commands import SERVE, BackendFlag

from ..core.devices import resolve_device
from ..data.run_folder import RunFolder
from ..evaluation.view_server import serve
from .arguments import add_cpu_threads, add_device, positive_float, use_cpu_threads

NAME = SERVE
HELP = "keep a trained run loaded and render the views a parent asks for on stdin (Blender's live view)"
# The default idle limit: a server nobody asks anything of for ten minutes stops.
IDLE_SECONDS = 600.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="the run folder (finished, or still training: newer checkpoints load)")
    parser.add_argument(BackendFlag.FRAMES, type=Path, required=True,
                        help="an existing folder for the frame files (the parent's: it makes and removes it)")
    add_device(parser)
    add_cpu_threads(parser)
    parser.add_argument(BackendFlag.IDLE_SECONDS, type=positive_float, default=IDLE_SECONDS,
                        help="stop after this many seconds without a request")


def run(args: argparse.Namespace) -> int:
    use_cpu_threads(args)
    reason = serve(RunFolder(args.run), args.frames, resolve_device(args.device), args.idle_seconds)
    print(f"serve: stopped: {reason}", file=sys.stderr)
    return 0
