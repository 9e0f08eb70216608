"""The Plenoxels field (Fridovich-Keil et al. 2022): a sparse voxel grid holding, at each
vertex, a density and the colour's spherical harmonics (degree 2: 9 coefficients a colour
channel, 27 in all), read trilinearly; no network.

Density is ``scale · softplus(gain · v + shift)`` of the interpolated value (TensoRF's form, as
the grid field: a new field starts near-empty, and a cell's largest density is at a corner, so
the occupancy grid is exact); colour is ``sigmoid`` of each channel's harmonics at the viewing
direction, times its own gain. Training goes coarse to fine; at each growth the vertices of cells that hold no
density (with a margin) are pruned, so memory and the optimiser's work follow the scene's
surface, not the box. Total variation on density and colour over a random set of vertices
each step keeps the grid smooth where rays are few (Plenoxels' regulariser).

On the CPU the grid is read and differentiated by ``kernels/sparse_grid.c`` and updated row
by row (``SparseRowAdam``); what a sample reads is 8 rows of 32 floats, against the factorised
grids' ~1 150 values and a network for the grid field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..core.field_functions import RayColourFn
from ..core.scene_bounds import SceneBounds
from ..field_components.grid_growth import cubic_vertices, grown_resolution, stage_of
from ..field_components.sparse_grid import SparseVoxelGrid, Vertices
from ..field_components.spherical_harmonics import sh_basis, sh_count
from ..field_components.total_variation import total_variation
from ..model_components.compiled_march import SparseDensity
from .base import MarchableField, SampleCost, VertexOccupancy


@dataclass(frozen=True)
class PlenoxelFieldConfig:
    # Vertices along the box's longest side at the end of training (cubic cells), grown from
    # initial_resolution one step at each of upsample_iterations.
    resolution: int = 256
    initial_resolution: int = 128
    upsample_iterations: tuple[int, ...] = (1000,)
    # Once the box is fitted to the scene, cells keep the count the schedule gives over the box
    # the field was built over (they shrink with the box), never below this side (world units;
    # the preset sets a training pixel's footprint). 0: no floor.
    finest_cell: float = 0.0
    sh_degree: int = 2
    density_shift: float = -10.0
    density_scale: float = 25.0
    # The grid holds density / density_gain and harmonics / colour_gain: Adam moves a row by
    # about the learning rate a step whatever its gradient, and a vertex is touched only by the
    # few rays near it, so its values need larger steps than a shared factorised grid's (lego,
    # 2 minutes: 21.0 dB with these, 14.7 with half; the 40×40 demo, 300 steps: 29.8 and 32.7).
    density_gain: float = 20.0
    colour_gain: float = 10.0
    # Total variation (mean squared difference to each axis' next vertex) over tv_vertices
    # random kept vertices a step, weighted per channel.
    tv_density: float = 1e-3
    tv_colour: float = 1e-3
    tv_vertices: int = 16384
    # Pruning at a growth: a cell is kept where its density could reach prune_alpha over one
    # march step (never above the mean density: a young field is never pruned to nothing),
    # and within prune_margin cells of one that is. Rendering's threshold: the occupancy grid's
    # 1e-4 keeps a young field's haze (on lego it kept 82 % of the vertices at the growth).
    prune_alpha: float = 1e-2
    prune_margin: int = 1


class PlenoxelField(VertexOccupancy, MarchableField):
    """``density(x [P,3]) -> [P]`` and ``colour(x [P,3], d [P,3]) -> [P,3]`` from a sparse
    voxel grid of density and spherical harmonics. The occupancy grid's cells are the grid's."""

    SETTINGS_GROUP = "plenoxels"
    Config = PlenoxelFieldConfig
    BACKWARD_WORK = 1  # each corner row's gradient is its weight times the sample's: no value read again

    def __init__(self, config: PlenoxelFieldConfig, box: SceneBounds) -> None:
        super().__init__(box)
        self.config = config
        self.coefficients = sh_count(config.sh_degree)
        self.grid = SparseVoxelGrid(1 + 3 * self.coefficients, self.vertices_at(config.initial_resolution))
        self.grown_to = config.initial_resolution
        self._note: str | None = None

    @property
    def vertices(self) -> Vertices:
        return self.grid.vertices

    @property
    def resolution(self) -> int:
        return max(self.vertices)

    def vertices_at(self, resolution: int) -> Vertices:
        return cubic_vertices(resolution, self.extent, self.built_extent, self.config.finest_cell)

    def resolution_after(self, iteration: int) -> int:
        config = self.config
        return grown_resolution(config.initial_resolution, config.resolution, config.upsample_iterations, iteration)

    # Density and colour.

    def density_from_values(self, value: Tensor) -> Tensor:
        config = self.config
        return config.density_scale * F.softplus(config.density_gain * value.float() + config.density_shift)

    def density(self, x: Tensor) -> Tensor:
        normalised = self.normalise(x)
        if torch.is_grad_enabled() and self.grid.values.requires_grad:
            return self.density_from_values(self.grid(normalised)[:, 0])
        return self.density_from_values(self.grid.channel(normalised, 0))

    def colour_from_values(self, harmonics: Tensor, basis: Tensor) -> Tensor:
        """``sigmoid`` of each channel's harmonics ``[P, 3·K]`` at the basis ``[P, K]``."""
        per_channel = harmonics.reshape(-1, 3, self.coefficients)
        return torch.sigmoid(self.config.colour_gain * (per_channel * basis[:, None, :]).sum(dim=-1))

    def colour(self, x: Tensor, directions: Tensor) -> Tensor:
        values = self.grid(self.normalise(x))
        return self.colour_from_values(values[:, 1:], sh_basis(directions, self.config.sh_degree))

    def forward(self, x: Tensor, directions: Tensor, coloured: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Density and colour from one read of the grid (every channel of every point)."""
        values = self.grid(self.normalise(x))
        density = self.density_from_values(values[:, 0])
        if coloured is not None:
            values, directions = values.index_select(0, coloured), directions.index_select(0, coloured)
        return density, self.colour_from_values(values[:, 1:], sh_basis(directions, self.config.sh_degree))

    def ray_colour(self, directions: Tensor, dtype: torch.dtype = torch.float32) -> RayColourFn:
        """Colour for inference: the harmonics' basis once a ray."""
        basis = sh_basis(directions, self.config.sh_degree)

        @torch.no_grad()
        def colour(x: Tensor, ray: Tensor) -> Tensor:
            return self.colour_from_values(self.grid(self.normalise(x))[:, 1:], basis.index_select(0, ray))

        return colour

    def sample_cost(self) -> dict[str, SampleCost]:
        width = self.grid.values.shape[1]
        colour_flops = 2 * 3 * self.coefficients + 4 * self.coefficients  # the sums, and the basis
        field = SampleCost(8 * width, 2 * 8 * width + colour_flops)
        return {"density": SampleCost(8, 16), "colour": field, "field": field, "frozen density": SampleCost(8, 16)}

    # What the march reads.

    @torch.no_grad()
    def vertex_density(self) -> Tensor:
        return self.density_from_values(self.grid.dense(0))

    @torch.no_grad()
    def density_volume(self) -> Tensor:
        """The density's pre-activation (less its shift) at every vertex ``[1, 1, Nz, Ny, Nx]``
        (a pruned vertex: 0, as the grid reads it): a trilinear read of it is the grid's."""
        return (self.config.density_gain * self.grid.dense(0)).permute(2, 1, 0)[None, None].contiguous()

    def density_from_volume(self, volume: Tensor, x: Tensor, directions: Tensor | None = None) -> Tensor:
        grid = self.normalise(x).view(1, -1, 1, 1, 3)
        return self.density_from_values(
            F.grid_sample(volume, grid, mode="bilinear", align_corners=True).view(-1) / self.config.density_gain)

    def volume_activation(self) -> tuple[str, float, float]:
        return "softplus", self.config.density_scale, self.config.density_shift

    def compiled_density(self) -> SparseDensity | None:
        """The density channel for the compiled training march (CPU, float32, a C compiler)."""
        config = self.config
        return SparseDensity.of(self.grid, config.density_scale, config.density_shift, config.density_gain)

    def encoding_parameters(self) -> list[nn.Parameter]:
        return [self.grid.values]

    # Training.

    def regularisation(self, generator: torch.Generator | None = None) -> Tensor | None:
        config = self.config
        if config.tv_vertices <= 0 or (config.tv_density <= 0 and config.tv_colour <= 0):
            return None
        weights = torch.full((self.grid.values.shape[1],), config.tv_colour, device=self.grid.values.device)
        weights[0] = config.tv_density
        weights[self.grid.channels:] = 0.0
        return total_variation(self.grid, weights, config.tv_vertices, generator)

    def coarse_detail(self) -> float | None:
        if self.grown_to >= self.config.resolution:
            return None
        return min(side / cells for side, cells in zip(self.extent, self.occupancy_cells()))

    def before_step(self, scheduled: int, steps_left: float | None = None) -> bool:
        """Grow on schedule, pruning the vertices of empty cells."""
        resolution = self.resolution_after(scheduled)
        if resolution == self.grown_to:
            return False
        before = self.grid.rows
        self._regrid(self.vertices_at(resolution), (-1.0,) * 3, (1.0,) * 3)
        self.grown_to = resolution
        self._note = (f"sparse grid grown to {' × '.join(map(str, self.vertices))} vertices, {self.grid.rows:,} kept "
                      f"({self.grid.rows / math.prod(self.vertices):.1%}; {before:,} before)")
        return True

    def fit_box(self, box: SceneBounds) -> bool:
        corners = self.normalise(torch.tensor([box.box_min, box.box_max], dtype=torch.float32,
                                              device=self.box_min.device)).tolist()
        self._set_box(box)
        self._regrid(self.vertices_at(self.grown_to), tuple(corners[0]), tuple(corners[1]))
        return True

    def resize(self, vertices: Vertices) -> None:
        self._regrid(vertices, (-1.0,) * 3, (1.0,) * 3)

    @torch.no_grad()
    def _regrid(self, vertices: Vertices, low: tuple, high: tuple) -> None:
        """The grid resampled onto ``vertices`` over ``[low, high]`` (normalised), keeping the
        new vertices that lie in or near a cell holding density now."""
        kept_cells = self._cells_to_keep()
        device = kept_cells.device
        axes = []
        for axis, count in enumerate(vertices):
            position = torch.linspace(low[axis], high[axis], count, device=device)  # normalised
            cell = ((position + 1.0) * 0.5 * kept_cells.shape[axis]).floor().long()
            axes.append(cell.clamp(0, kept_cells.shape[axis] - 1))
        keep = kept_cells[axes[0][:, None, None], axes[1][None, :, None], axes[2][None, None, :]]
        self.grid.take(self.grid.resampled(vertices, low, high, keep))

    @torch.no_grad()
    def _cells_to_keep(self) -> Tensor:
        """Cells ``[Gx, Gy, Gz]`` whose density could reach ``prune_alpha`` over a march step,
        widened by ``prune_margin`` cells."""
        cell_max, mean = self.occupancy_estimate()
        step = self.march_step or min(side / cells for side, cells in zip(self.extent, self.occupancy_cells()))
        threshold = min(-math.log1p(-self.config.prune_alpha) / step, mean)
        kept = (cell_max >= threshold).float()[None, None]
        margin = self.config.prune_margin
        if margin > 0:
            kept = F.max_pool3d(kept, 2 * margin + 1, stride=1, padding=margin)
        return kept[0, 0] > 0

    def take_note(self) -> str | None:
        note, self._note = self._note, None
        return note

    def match_state(self, state: dict[str, Tensor]) -> bool:
        """Take the box, vertices and kept rows a checkpoint was saved with."""
        changed = self._take_box(state)
        links, values = state["grid.links"], state["grid.values"]
        if tuple(links.shape) != self.vertices or values.shape[0] != self.grid.rows:
            self.grid.take_shapes(tuple(links.shape), values.shape[0])  # type: ignore[arg-type]
            changed = True
        config = self.config
        self.grown_to = stage_of(config.initial_resolution, config.resolution, config.upsample_iterations,
                                 self.vertices_at, self.vertices)
        return changed
