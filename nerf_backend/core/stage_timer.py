"""Seconds spent in each named stage of a training step or a render: ``bench-step``'s profile.

Off by default, when ``stage(name)`` costs one context a stage. ``StageTimer`` turns it on
for a block; on a GPU it synchronises the device at each stage's edges so that a stage's
time is its own. Only a profile waits for the device so: a normal run never does inside a step.

Example:
    >>> import torch
    >>> with StageTimer(torch.device("cpu")) as timer:
    ...     with stage("sum", items=1000):
    ...         _ = torch.ones(1000).sum()
    >>> timer.items["sum"], timer.seconds["sum"] > 0
    (1000, True)
"""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from typing import Callable, Iterator

import torch

from .devices import synchronise

_active: "StageTimer | None" = None


class StageTimer:
    """Collects ``seconds[name]`` and ``items[name]`` (samples, rays, parameters: what the
    stage worked on) of every ``stage`` run while it is entered."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.seconds: dict[str, float] = defaultdict(float)
        self.items: dict[str, int] = defaultdict(int)

    def __enter__(self) -> "StageTimer":
        global _active
        _active = self
        return self

    def __exit__(self, *exc) -> None:
        global _active
        _active = None


@contextmanager
def stage(name: str, items: "int | torch.Tensor | Callable[[], int]" = 0) -> Iterator[None]:
    """Time the block as stage ``name`` when a ``StageTimer`` is entered; else nothing.
    ``items`` may be a tensor (a count on the device) or a function: either is read only
    while profiling, so a normal run neither waits for the device nor counts."""
    timer = _active
    if timer is None:
        yield
        return
    synchronise(timer.device)
    start = time.perf_counter()
    try:
        yield
    finally:
        synchronise(timer.device)
        timer.seconds[name] += time.perf_counter() - start
        timer.items[name] += int(items() if callable(items) else items)


def count(name: str, items: "int | Callable[[], int]") -> None:
    """Add ``items`` to ``name``'s count (no time) while profiling: work a stage did that its
    own count does not say (the grid rows a training step touched)."""
    timer = _active
    if timer is not None:
        timer.items[name] += int(items() if callable(items) else items)
