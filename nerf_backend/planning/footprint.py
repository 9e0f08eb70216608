"""How fine a grid the training images can pin down: a pixel's footprint on the scene and the
vertices that resolve it (pure maths for the rules in ``rules.py``).

Example (100×100 views at radius 4, focal 138.9: a pixel covers 0.0288 units):
    >>> round(4 / 138.9, 4)
    0.0288
    >>> pixel_resolution(4 / 138.9, (2.0, 2.0, 2.0))[0]
    71
"""

from __future__ import annotations

import math

import torch

from ..core.scene_bounds import SceneBounds
from ..data.dataset import DatasetSplit

MIN_RESOLUTION, MAX_RESOLUTION = 32, 256
# A budget this long grows the grid up to LONG_BUDGET_RESOLUTION instead (docs/benchmarks_lego.md,
# "A finer grid for a longer budget"): more vertices need more steps to fill in, and make every
# view slower to render.
LONG_BUDGET_SECONDS = 1800.0
LONG_BUDGET_RESOLUTION = 384
FINEST_REASON = (
    "measured on lego at 800×800 on 2 CPU cores: 384 vertices along the longest side scored 35.00 dB after 30 "
    "minutes against 256's 34.54, and 33.04 after 10 as 256 did, while its views rendered 1.4 times slower "
    "(17.0-17.4 s for 13 views against 11.7-12.3)")


def pixel_footprint(split: DatasetSplit, box: SceneBounds) -> float:
    """Mean size (world units) of one pixel at the box's centre, over the training cameras."""
    centre = (torch.tensor(box.box_min) + torch.tensor(box.box_max)) / 2
    distances = (split.poses[:, :3, 3] - centre).norm(dim=-1)
    focal = (split.intrinsics.fl_x + split.intrinsics.fl_y) / 2
    return float(distances.mean()) / focal


def finest_resolution(budget_seconds: float | None) -> tuple[int, str]:
    """The most vertices along the box's longest side a grid grows to within a time budget
    (None: no budget), and why.

    Example:
        >>> finest_resolution(None)[0], finest_resolution(600.0)[0], finest_resolution(1800.0)[0]
        (256, 256, 384)
    """
    if budget_seconds is not None and budget_seconds >= LONG_BUDGET_SECONDS:
        return LONG_BUDGET_RESOLUTION, (f"a budget of {budget_seconds / 60:g} minutes (at least "
                                        f"{LONG_BUDGET_SECONDS / 60:g}) grows it up to {LONG_BUDGET_RESOLUTION}: "
                                        f"{FINEST_REASON}")
    budget = "no time budget" if budget_seconds is None else f"a budget of {budget_seconds / 60:g} minutes"
    return MAX_RESOLUTION, (f"{budget} (under {LONG_BUDGET_SECONDS / 60:g}) grows it up to {MAX_RESOLUTION}: "
                            f"{FINEST_REASON}")


def pixel_resolution(footprint: float, sides: tuple[float, float, float], cubic_cells: bool = True,
                     most: int = MAX_RESOLUTION) -> tuple[int, str]:
    """Vertices along the box's longest side that resolve a pixel of ``footprint`` (world
    units) in a box of ``sides`` (with cubic cells: a cube's cells spread over the box), within
    [MIN_RESOLUTION, most], and why."""
    extent = max(sides)
    per_pixel = math.ceil(extent / footprint) + 1
    reason = (f"a pixel covers {footprint:.4f} units at the scene's centre and the box is {extent:.3f} across: "
              f"{per_pixel} vertices a side resolve every pixel")
    wanted = per_pixel
    if cubic_cells:
        # The cells a cube of that resolution would have, spread over the box with cubic
        # cells: a flat or long box gets finer cells along its long sides for the same cost.
        cell = math.prod(sides) ** (1 / 3) / (per_pixel - 1)
        wanted = round(extent / cell) + 1
        if wanted != per_pixel:
            reason += (f"; the box is not a cube ({' × '.join(f'{side:.2f}' for side in sides)}): the "
                       f"{(per_pixel - 1) ** 3:,} cells of a {per_pixel}-vertex cube, spread over it as cubic "
                       f"cells of {cell:.4f}, give {wanted} vertices along its longest side")
    clamped = max(MIN_RESOLUTION, min(most, wanted))
    if clamped != wanted:
        reason += f" (clamped to [{MIN_RESOLUTION}, {most}])"
    return clamped, reason
