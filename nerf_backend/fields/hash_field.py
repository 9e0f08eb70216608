"""Instant-NGP's field: a multiresolution hash encoding of position read by a small density
MLP, whose extra outputs (geometry features) feed a colour MLP with the view direction.

Density is ``exp`` of the MLP's first output (Instant-NGP's activation; its gradient is
clamped so a large value cannot blow up a step). The occupancy grid's cells have no relation
to the hash grids, so each cell's density is estimated, as Instant-NGP does: at one random
point per cell at each update, kept as the maximum of that and the decayed previous estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..core.scene_bounds import SceneBounds, vertices_for
from ..field_components.encodings import PositionalEncoding
from ..field_components.hash_encoding import HashEncoding
from .base import MarchableField, SampleCost, mlp_flops


@dataclass(frozen=True)
class HashFieldConfig:
    levels: int = 16
    features_per_level: int = 2
    # 2^16 rows a level: 2M parameters in all, small enough for CPU caches to matter less
    # (the paper uses 2^19 on a GPU).
    log2_table_size: int = 16
    base_resolution: int = 16
    # The finest level's cells along the box's longest side.
    max_resolution: int = 512
    hidden_width: int = 64
    geometry_features: int = 15
    view_dependent: bool = True
    direction_frequencies: int = 4
    # The occupancy grid's cells along the box's longest side (the march's step follows).
    occupancy_resolution: int = 64
    # Each update keeps max(decay · previous estimate, new sample) per cell.
    occupancy_decay: float = 0.95


class _TruncatedExp(torch.autograd.Function):
    """``exp(x)`` whose gradient uses ``exp(min(x, 15))``: a large density cannot produce an
    overflowing gradient (Instant-NGP's trunc_exp)."""

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=80.0))  # float32's exp overflows past ~88

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:  # type: ignore[override]
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(-15.0, 15.0))


class HashField(MarchableField):
    """``density(x [P,3]) -> [P]`` and ``colour(x [P,3], d [P,3]) -> [P,3]`` in world space."""

    SETTINGS_GROUP = "hash"
    Config = HashFieldConfig
    # Each sample reads 16 levels × 8 corners: smaller chunks keep that in memory.
    render_chunk = 2048

    def __init__(self, config: HashFieldConfig, box: SceneBounds) -> None:
        super().__init__(box)
        self.config = config
        self.encoding = HashEncoding(config.levels, config.features_per_level, config.log2_table_size,
                                     config.base_resolution, config.max_resolution)
        self.density_mlp = nn.Sequential(
            nn.Linear(self.encoding.out_dims, config.hidden_width), nn.ReLU(inplace=True),
            nn.Linear(config.hidden_width, 1 + config.geometry_features),
        )
        self.direction_encoding = PositionalEncoding(3, config.direction_frequencies)
        colour_in = config.geometry_features + (self.direction_encoding.out_dims if config.view_dependent else 0)
        self.colour_mlp = nn.Sequential(
            nn.Linear(colour_in, config.hidden_width), nn.ReLU(inplace=True),
            nn.Linear(config.hidden_width, config.hidden_width), nn.ReLU(inplace=True),
            nn.Linear(config.hidden_width, 3),
        )
        cells = self.occupancy_cells()
        # The decayed maximum of the estimates; until the first, the occupancy grid marks all occupied.
        self.register_buffer("cell_density", torch.zeros(cells))
        # Counts the estimates: each draws its points from a generator seeded with it, so a resumed
        # run draws what an uninterrupted one would (the global generator is not checkpointed).
        self.register_buffer("estimates", torch.zeros((), dtype=torch.long))

    def _features(self, x: Tensor) -> Tensor:
        unit = (self.normalise(x) + 1.0) * 0.5
        return self.density_mlp(self.encoding(unit))

    def density(self, x: Tensor) -> Tensor:
        return _TruncatedExp.apply(self._features(x)[..., 0].float())

    def colour(self, x: Tensor, directions: Tensor) -> Tensor:
        return self._colour_from(self._features(x)[..., 1:], directions)

    def _colour_from(self, features: Tensor, directions: Tensor) -> Tensor:
        if self.config.view_dependent:
            features = torch.cat([features, self.direction_encoding(directions).to(features.dtype)], dim=-1)
        return torch.sigmoid(self.colour_mlp(features).float())

    def forward(self, x: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """Density and colour from one read of the hash grids (the costly part on a CPU)."""
        features = self._features(x)
        return _TruncatedExp.apply(features[..., 0].float()), self._colour_from(features[..., 1:], directions)

    def occupancy_cells(self) -> tuple[int, int, int]:
        vertices = vertices_for(self.config.occupancy_resolution + 1, self.extent)
        return tuple(n - 1 for n in vertices)  # type: ignore[return-value]

    def encoding_parameters(self) -> list[nn.Parameter]:
        return list(self.encoding.parameters())

    def sample_cost(self) -> dict[str, SampleCost]:
        # Every level reads its 8 corners' features; density and colour share that read.
        reads = self.config.levels * 8 * self.config.features_per_level
        features = SampleCost(reads, 2 * reads + mlp_flops(self.density_mlp))
        both = features + SampleCost(0, mlp_flops(self.colour_mlp))
        return {"density": features, "colour": both, "field": both, "frozen density": features}

    @torch.no_grad()
    def occupancy_estimate(self) -> tuple[Tensor, float]:
        cells = torch.tensor(self.cell_density.shape, device=self.box_min.device)
        index = torch.stack(torch.meshgrid(*(torch.arange(int(n), device=cells.device) for n in cells),
                                           indexing="ij"), dim=-1).view(-1, 3)
        generator = torch.Generator(device=cells.device).manual_seed(int(self.estimates))
        self.estimates += 1
        unit = (index + torch.rand(index.shape, device=cells.device, generator=generator)) / cells
        points = self.box_min + unit * (self.box_max - self.box_min)
        sampled = torch.cat([self.density(chunk) for chunk in points.split(65536)]).view(self.cell_density.shape)
        self.cell_density.copy_(torch.maximum(self.cell_density * self.config.occupancy_decay, sampled))
        return self.cell_density, float(sampled.mean())

    def cell_max_density(self) -> Tensor | None:
        return self.cell_density if int(self.estimates) > 0 else None
