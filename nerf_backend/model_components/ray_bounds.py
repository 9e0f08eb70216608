"""Where along each ray the scene can be: the protocol's fixed near/far, or the entry and
exit of the scene's bounding box (the scene is known, so samples are not spent outside it)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.scene_bounds import SceneBounds
from .compiled_march import ray_box_stretch

PROTOCOL_NEAR, PROTOCOL_FAR = 2.0, 6.0
# Without a scene profile: the box the nerf_synthetic scenes are normalised into.
PROTOCOL_BOX = SceneBounds((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
# Room around the geometry's tight bounds, as a fraction of the box's largest side.
BOX_PADDING = 0.05


@dataclass(frozen=True)
class RayBounds:
    """Either a fixed ``[near, far]`` for every ray or a box each ray is clipped to."""

    near: float = PROTOCOL_NEAR
    far: float = PROTOCOL_FAR
    box: SceneBounds | None = None

    def describe(self) -> dict:
        if self.box is None:
            return {"kind": "protocol", "near": self.near, "far": self.far}
        return {"kind": "scene_box", "box_min": list(self.box.box_min), "box_max": list(self.box.box_max)}

    def __call__(self, origins: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """``t_near [R]``, ``t_far [R]`` for rays with unit ``directions``."""
        if self.box is None:
            t_near = torch.full(origins.shape[:1], self.near, device=origins.device, dtype=origins.dtype)
            return t_near, torch.full_like(t_near, self.far)
        box_min = torch.tensor(self.box.box_min, device=origins.device, dtype=origins.dtype)
        box_max = torch.tensor(self.box.box_max, device=origins.device, dtype=origins.dtype)
        return ray_box_stretch(origins, directions, box_min, box_max)


def choose_ray_bounds(kind: str, scene_bounds: SceneBounds | None) -> tuple[RayBounds, str]:
    """The ray bounds a run uses and the reason, for the run's config."""
    if kind == "scene" and scene_bounds is not None:
        return RayBounds(box=scene_bounds.padded(BOX_PADDING)), (
            f"scene_profile.json bounds padded by {BOX_PADDING:.0%} of their largest side"
        )
    if kind == "scene":
        return RayBounds(box=PROTOCOL_BOX), (
            "the dataset has no scene_profile.json: the box [-1.5, 1.5]³ the nerf_synthetic scenes fit in"
        )
    if kind == "protocol":
        return RayBounds(), "the protocol's near 2, far 6 (as the reference loaders)"
    raise ValueError(f"unknown ray bounds kind {kind!r}")
