"""Blender's world and the dataset's NeRF frame: ``datasets_gen`` records the similarity that
took the scene into the frame the model trained in (``world_to_nerf`` in ``scene_profile.json``:
``p_nerf = scale * p_blender + translation``, or a 4×4 ``matrix``); results go back through its
inverse."""

from __future__ import annotations

import torch
from torch import Tensor


def world_to_nerf_matrix(world_to_nerf: dict | None) -> Tensor:
    """The 4×4 (float64) of a dataset's ``world_to_nerf`` record; the identity where there is
    none (a dataset from another tool is in its own frame).

    Example:
        >>> world_to_nerf_matrix({"scale": 2.0, "translation": [0.0, 0.0, 1.0]})[:3].tolist()
        [[2.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 2.0, 1.0]]
    """
    if world_to_nerf is None:
        return torch.eye(4, dtype=torch.float64)
    if "matrix" in world_to_nerf:
        return torch.tensor(world_to_nerf["matrix"], dtype=torch.float64)
    matrix = torch.eye(4, dtype=torch.float64) * float(world_to_nerf.get("scale", 1.0))
    matrix[3, 3] = 1.0
    matrix[:3, 3] = torch.tensor(world_to_nerf.get("translation", [0.0, 0.0, 0.0]), dtype=torch.float64)
    return matrix
