"""Coarse to fine: a grid's vertex count along the box's longest side as training goes on,
grown geometrically from its initial count to its final one, a step at each scheduled
iteration (cheap early steps, detail later; DVGO's and TensoRF's schedule).

Example:
    >>> [grown_resolution(32, 128, (100, 200), step) for step in (0, 100, 150, 200)]
    [32, 64, 64, 128]
"""

from __future__ import annotations


def grown_resolution(initial: int, final: int, upsample_iterations: tuple[int, ...], iteration: int) -> int:
    """The vertex count once ``iteration`` steps of the schedule have been taken."""
    done = sum(1 for at in upsample_iterations if iteration >= at)
    if done == 0:
        return initial
    return round(initial * (final / initial) ** (done / len(upsample_iterations)))
