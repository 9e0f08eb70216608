"""Coarse to fine: a grid's vertex count along the box's longest side as training goes on,
grown geometrically from its initial count to its final one, a step at each scheduled
iteration (cheap early steps, detail later; DVGO's and TensoRF's schedule).

Example:
    >>> [grown_resolution(32, 128, (100, 200), step) for step in (0, 100, 150, 200)]
    [32, 64, 64, 128]
"""

from __future__ import annotations

import math


def grown_resolution(initial: int, final: int, upsample_iterations: tuple[int, ...], iteration: int) -> int:
    """The vertex count once ``iteration`` steps of the schedule have been taken."""
    done = sum(1 for at in upsample_iterations if iteration >= at)
    if done == 0:
        return initial
    return round(initial * (final / initial) ** (done / len(upsample_iterations)))


def cubic_vertices(resolution: int, extent: tuple[float, ...], built_extent: tuple[float, ...],
                   finest_cell: float = 0.0) -> tuple[int, int, int]:
    """Vertices on each axis of a grid over ``extent`` with cubic cells, for the schedule's
    ``resolution`` (vertices along the longest side of the box the grid was built over,
    ``built_extent``): over a box since narrowed, as many cells as that gives over the built
    box, so the cells shrink with it, though never below ``finest_cell`` (0: no floor).

    Example:
        >>> cubic_vertices(65, (2.0, 2.0, 0.5), (2.0, 2.0, 0.5))
        (65, 65, 17)
    """
    built_cell = max(built_extent) / (resolution - 1)
    shrink = (math.prod(extent) / math.prod(built_extent)) ** (1 / 3)
    cell = max(built_cell * shrink, min(built_cell, finest_cell))
    return tuple(max(2, round(side / cell) + 1) for side in extent)  # type: ignore[return-value]


def stage_of(initial: int, final: int, upsample_iterations: tuple[int, ...], vertices_at, vertices) -> int:
    """The schedule's resolution that a grid of ``vertices`` stands for (the stage whose
    ``vertices_at(resolution)`` it has: a checkpoint's grid), else the final one.

    Example:
        >>> stage_of(32, 128, (100, 200), lambda r: (r, r, r), (64, 64, 64))
        64
    """
    stages = {grown_resolution(initial, final, upsample_iterations, at) for at in (0, *upsample_iterations)}
    return next((r for r in sorted(stages) if vertices_at(r) == vertices), final)
