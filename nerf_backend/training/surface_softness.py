"""The surface preset's final softness, from the dataset's pixel size.

VolSDF's density outside the surface piles up along rays that graze it, so a silhouette lies
outside the distance's zero level (1.4 cells on a sphere of 48 cells with β half a cell; the
offset grows with β) and training pulls the surface inward by as much (docs/benchmarks.md, "Why the surface sits inside"). Where the images' pixels
are finer than the grid's cells they pin silhouettes more tightly than that bias, and a sharper
final β moves the surface out: at 800×800 (a pixel 0.36 of a cell) a final β of a quarter cell
took the F-score from 0.486 to 0.611 on A.blend and from 0.323 to 0.495 on RobotExpressive (PSNR
−0.83 and +0.44 dB). Where pixels are coarser than cells (100×100: 2.9 cells) the same
sharpening cost 1.7-3.5 dB for no F-score, so β stays at half a cell there.

Example (100×100 views at radius 4: a pixel is several cells, β stays at half a cell):
    >>> import torch
    >>> from nerf_backend.configs.presets import PRESETS
    >>> from nerf_backend.core.cameras import Intrinsics
    >>> from nerf_backend.core.scene_bounds import SceneBounds
    >>> from nerf_backend.data.dataset import DatasetSplit
    >>> poses = torch.eye(4)[None].clone(); poses[:, 2, 3] = 4.0
    >>> split = DatasetSplit("train", Intrinsics(100, 100, 138.9, 138.9, 50.0, 50.0), poses,
    ...                      torch.zeros((1, 100, 100, 4), dtype=torch.uint8), [])
    >>> config, decision = surface_softness(PRESETS["surface"], split, SceneBounds((-1,) * 3, (1,) * 3))
    >>> config.surface.final_beta_cells
    0.5
"""

from __future__ import annotations

import dataclasses

from ..configs.train_config import TrainConfig
from ..core.scene_bounds import SceneBounds, vertices_for
from ..data.dataset import DatasetSplit
from .auto import pixel_footprint
from .decision import decide

# Final β in cells: this share of a pixel's footprint in cells, within these bounds (measured
# at the two ends: 0.36 of a cell a pixel → a quarter cell; 2.9 cells → half a cell).
BETA_PER_PIXEL = 0.7
SHARPEST_BETA_CELLS, SOFTEST_BETA_CELLS = 0.25, 0.5


def surface_softness(config: TrainConfig, split: DatasetSplit, box: SceneBounds,
                     user_set: frozenset[str] = frozenset()) -> tuple[TrainConfig, dict]:
    """``config`` (a surface preset) with its final β set from the pixel's footprint, and the
    decision with its reason (the user's ``--set surface.final_beta_cells`` is kept)."""
    surface = config.surface
    sides = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))
    cell = min(side / (n - 1) for side, n in zip(sides, vertices_for(surface.resolution, sides)))
    pixel_cells = pixel_footprint(split, box) / cell
    chosen = round(min(SOFTEST_BETA_CELLS, max(SHARPEST_BETA_CELLS, BETA_PER_PIXEL * pixel_cells)), 3)
    reason = (f"a pixel covers {pixel_cells:.2f} cells of the final grid at the scene's centre: the final β is "
              f"{BETA_PER_PIXEL} of that within [{SHARPEST_BETA_CELLS}, {SOFTEST_BETA_CELLS}] cells (sharper where "
              "pixels resolve VolSDF's silhouette bias)")
    value, record = decide("surface.final_beta_cells", chosen, reason, config, user_set)
    shaped = config.with_settings(surface=dataclasses.replace(surface, final_beta_cells=value))
    return shaped, {"surface_softness": record}
