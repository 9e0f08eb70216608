"""What the scene's surface is made of and which way it faces, where Blender said so: the
occupancy prior's appearance regions and the true surface's normals, resampled onto a coarse
grid over the prior's box and kept as the field's buffers (so a checkpoint renders without its
dataset). The region-aware colour (``GridAppearance``) reads them at every sample.

A coarse grid (``OccupancyPrior.surface_grid``), because both vary slowly where it matters: a
region is constant over a material's surface, and the normals are read trilinearly. At 128
cells a side it is about 8 MB, beside the prior's 256.

Example:
    >>> import torch
    >>> facts = SurfaceFacts()
    >>> facts.region_at(torch.zeros(2, 3)).tolist(), facts.normal_at(torch.zeros(1, 3)).tolist()  # none yet
    ([0, 0], [[0.0, 0.0, 0.0]])
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class SurfaceFacts(nn.Module):
    """Buffers: ``regions`` uint8 ``[nx, ny, nz]`` (indices of ``APPEARANCE_REGIONS``),
    ``normals`` float16 ``[3, nz, ny, nx]`` (unit where a surface is near, else zero; laid out
    for ``grid_sample``) and ``box`` ``[2, 3]`` (the grid's corners)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("regions", torch.zeros((1, 1, 1), dtype=torch.uint8))
        self.register_buffer("normals", torch.zeros((3, 1, 1, 1), dtype=torch.float16))
        self.register_buffer("box", torch.tensor([[-1.0] * 3, [1.0] * 3]))

    def set(self, regions: Tensor, normals: Tensor, box_min: Tensor, box_max: Tensor) -> None:
        """Take ``regions`` uint8 ``[nx, ny, nz]`` and ``normals`` ``[nx, ny, nz, 3]`` over the
        box ``[box_min, box_max]`` (``OccupancyPrior.surface_grid``)."""
        device = self.box.device
        self.regions = regions.to(device, torch.uint8)
        self.normals = normals.permute(3, 2, 1, 0).contiguous().to(device, torch.float16)
        self.box = torch.stack([box_min, box_max]).to(device, torch.float32)

    def match_state(self, state: dict[str, Tensor], prefix: str) -> None:
        """Take the buffers' shapes a checkpoint was saved with (its values are loaded next)."""
        for name in ("regions", "normals"):
            saved = state.get(prefix + name)
            if saved is not None and saved.shape != getattr(self, name).shape:
                setattr(self, name, torch.zeros_like(saved, device=self.box.device))

    def region_at(self, x: Tensor) -> Tensor:
        """Each point's region ``[P]`` (int64; 0 outside the grid)."""
        low, high = self.box[0], self.box[1]
        shape = torch.tensor(self.regions.shape, device=x.device)
        cells = ((x - low) / (high - low) * shape).floor().long()
        inside = ((cells >= 0) & (cells < shape)).all(dim=1)
        cells = torch.minimum(cells.clamp(min=0), shape - 1)
        return self.regions[cells[:, 0], cells[:, 1], cells[:, 2]].long() * inside

    def normal_at(self, x: Tensor) -> Tensor:
        """Each point's surface normal ``[P, 3]`` (float32, read trilinearly; zero where no
        surface is near)."""
        normals = self._normals_float()
        if normals is None or x.shape[0] == 0:
            return x.new_zeros(x.shape, dtype=torch.float32)
        low, high = self.box[0], self.box[1]
        grid = ((x - low) / (high - low) * 2.0 - 1.0).view(1, -1, 1, 1, 3)  # grid_sample's (x, y, z)
        normal = F.grid_sample(normals, grid.float(), mode="bilinear", padding_mode="zeros",
                               align_corners=False).view(3, -1).t()
        length = normal.norm(dim=1, keepdim=True)
        # Where the cells around hold no surface the interpolated vector fades to zero: none there.
        return torch.where(length > 0.25, normal / length.clamp(min=1e-6), torch.zeros_like(normal))

    def _normals_float(self) -> Tensor | None:
        """The normals as float32 ``[1, 3, nz, ny, nx]`` for ``grid_sample`` (None where there are
        none), kept while the buffer is unchanged: converting them is a pass over the whole
        grid, which every training step's lookup would repeat."""
        key = (self.normals.data_ptr(), self.normals._version, self.normals.device)
        cached = getattr(self, "_float_cache", None)
        if cached is None or cached[0] != key:
            values = self.normals[None].float()
            cached = self._float_cache = (key, values if bool(values.any()) else None)
        return cached[1]
