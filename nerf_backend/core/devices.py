"""Choosing the compute device: CUDA, then Apple's MPS, then the CPU; and the precision of
inference's colour network on it."""

from __future__ import annotations

import time
from functools import cache

import torch

from .errors import NerfError


# The devices a run may name, fastest first (``auto`` takes the first present).
DEVICES = ("cuda", "mps", "cpu")


def present_devices() -> tuple[str, ...]:
    """The devices this torch build can use here, fastest first (the CPU always)."""
    mps = getattr(torch.backends, "mps", None)
    return tuple(name for name, present in (("cuda", torch.cuda.is_available()),
                                            ("mps", mps is not None and mps.is_available()), ("cpu", True))
                 if present)


def choose_device(name: str, present: tuple[str, ...]) -> tuple[torch.device, str]:
    """The device ``name`` asks for among ``present`` (``present_devices``'s), and why.
    ``auto`` picks the fastest present; naming an absent device is an error, not a silent
    fallback, so a user never trains on the CPU believing it is the GPU.

    Example:
        >>> choose_device("auto", ("cpu",))
        (device(type='cpu'), 'auto: no GPU (CUDA or MPS) is present, so the CPU')
        >>> choose_device("auto", ("cuda", "cpu"))[0]
        device(type='cuda')
    """
    if name == "auto":
        chosen = present[0]
        return torch.device(chosen), (f"auto: the fastest device present ({', '.join(present)})" if chosen != "cpu"
                                      else "auto: no GPU (CUDA or MPS) is present, so the CPU")
    if name not in DEVICES:
        raise NerfError(f"--device {name}: choose auto, cpu, cuda or mps")
    if name not in present:
        raise NerfError("--device cuda: this torch build sees no CUDA device" if name == "cuda"
                        else "--device mps: Apple's Metal (MPS) is not available here")
    return torch.device(name), f"asked for with --device {name}"


def resolve_device(name: str) -> torch.device:
    """``choose_device`` among the devices present here."""
    return choose_device(name, present_devices())[0]


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


def machine_record(device: torch.device) -> dict:
    """What computed a measurement, for its tables: torch's version, the CPU threads and the
    processor (the GPU's name, or the CPU's vector extensions, which decide its kernels)."""
    if device.type == "cuda":
        processor = torch.cuda.get_device_name(device)
    elif device.type == "mps":
        processor = "Apple GPU (MPS)"
    else:
        processor = f"CPU ({torch.backends.cpu.get_cpu_capability()})"
    return {"torch": torch.__version__, "threads": torch.get_num_threads(), "processor": processor}


def machine_words(machine: dict) -> str:
    """``machine_record`` in a table's words: ``torch 2.13.0+cpu on 2 threads, CPU (AVX512)``
    (a record made before the processor was kept has only its threads)."""
    words = f"torch {machine['torch']} on {machine['threads']} threads"
    return f"{words}, {machine['processor']}" if machine.get("processor") else words


# Inference's colour network runs in bfloat16 where that is this much faster than float32
# (measured once a process): a CPU with AVX512-BF16 or AMX, 3.5x on an AMD EPYC's 2 cores; an
# AVX2 CPU only emulates it, slower. Its products then round to 8 bits of mantissa: lego's
# 800×800 test views moved by under 0.01 dB (docs/benchmarks_lego.md).
BF16_MIN_SPEEDUP = 1.5


def colour_network_dtype(device: torch.device) -> torch.dtype:
    """The type inference's colour network computes in on ``device`` where it runs through
    PyTorch (the CPU's compiled colour pass, ``compiled_colour``, is float32): bfloat16 on a CPU whose
    bfloat16 products of the network's shape are measured ``BF16_MIN_SPEEDUP`` times faster
    than float32's, float32 elsewhere (GPUs included: their colour pass is not what a view
    waits on)."""
    return _cpu_colour_dtype() if device.type == "cpu" else torch.float32


@cache  # measured once a process
def _cpu_colour_dtype() -> torch.dtype:
    faster = _product_seconds(torch.float32) >= BF16_MIN_SPEEDUP * _product_seconds(torch.bfloat16)
    return torch.bfloat16 if faster else torch.float32


def _product_seconds(dtype: torch.dtype, rows: int = 8192, width: int = 64, repeats: int = 5) -> float:
    """The least time of a colour layer's product (``rows × width`` by ``width × width``)."""
    generator = torch.Generator().manual_seed(0)
    a = torch.randn(rows, width, generator=generator).to(dtype)
    b = torch.randn(width, width, generator=generator).to(dtype)
    a @ b  # the first call sets up the kernel
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return best
