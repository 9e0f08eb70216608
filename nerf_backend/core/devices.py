"""Choosing the compute device: CUDA, then Apple's MPS, then the CPU."""

from __future__ import annotations

import torch

from .errors import NerfError


def resolve_device(name: str) -> torch.device:
    """``auto`` picks the fastest present; naming an absent device is an error, not a
    silent fallback, so a user never trains on the CPU believing it is the GPU."""
    if name == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
            return torch.device("mps")
        return torch.device("cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise NerfError("--device cuda: this torch build sees no CUDA device")
    if name == "mps" and not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
        raise NerfError("--device mps: Apple's Metal (MPS) is not available here")
    if name not in ("cpu", "cuda", "mps"):
        raise NerfError(f"--device {name}: choose auto, cpu, cuda or mps")
    return torch.device(name)


def synchronise(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (nothing to wait for on the CPU): only for
    timing, never inside a step."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


# The types ``TrainConfig.precision`` may name; None: no autocast.
PRECISIONS: dict[str, torch.dtype | None] = {"float32": None, "bfloat16": torch.bfloat16, "float16": torch.float16}


def autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    """The autocast type of a run's ``precision`` on ``device`` (None for float32)."""
    if precision not in PRECISIONS:
        raise NerfError(f"precision {precision!r}: choose one of {', '.join(PRECISIONS)}")
    dtype = PRECISIONS[precision]
    if dtype is not None and not torch.amp.is_autocast_available(device.type):
        raise NerfError(f"precision {precision}: autocast is not available on {device.type}")
    return dtype
