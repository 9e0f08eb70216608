"""What several commands' parsers share: number types that refuse bad values in one line, and
the device, CPU threads, seed and LPIPS arguments (the bench commands' `--page`: page_option.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from nerf_contract.commands import BackendFlag

from ..metrics.lpips_metric import BACKBONE_FILE

DEVICES = ("auto", "cpu", "cuda", "mps")
DEVICE_HELP = "where to compute: auto takes CUDA, then Apple's MPS, then the CPU"
SEED_HELP = "seed of the model's initialisation and of the rays sampled"


def positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive whole number, got {text}")
    return value


def positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def add_device(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(BackendFlag.DEVICE, default="auto", choices=DEVICES, help=DEVICE_HELP)


def add_cpu_threads(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(BackendFlag.CPU_THREADS, type=positive_int, default=None, metavar="N",
                        help="threads for work on the CPU (default: one per core); the add-on leaves Blender a core, "
                             "since torch slows about 3x when another program takes one of the cores it uses")


def use_cpu_threads(args: argparse.Namespace) -> None:
    """Apply ``add_cpu_threads``' choice before any work."""
    if args.cpu_threads is not None:
        torch.set_num_threads(args.cpu_threads)


def add_seed(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=0, help=SEED_HELP)


def add_lpips_weights(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--lpips-weights", type=Path, default=None,
                        help=f"torchvision's AlexNet weights ({BACKBONE_FILE}) for LPIPS (default: torch hub's cache, "
                             "downloaded there on first use)")
    parser.add_argument("--lpips-linear", type=Path, default=None,
                        help="LPIPS v0.1 linear-layer weights (default: the ones in the lpips package)")
