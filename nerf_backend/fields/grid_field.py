"""The fast field: density and colour from factorised grids plus a small colour MLP.

Density is a linear read-out of one ``VectorMatrixGrid`` through a shifted softplus (so a
new field starts near-empty and smooth). Colour comes from a second grid's features
through a two-layer MLP, with the viewing direction's encoding as an input only when the
field is view-dependent. Colour is computed only where the caller asks (samples that carry
weight), which is where most of the speed of the fast preset comes from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..core.scene_bounds import SceneBounds
from ..core.tensor_keys import kept_derived
from ..core.field_functions import LitPassFn
from ..field_components.compiled_grid import density_components, read_grids
from ..field_components.compiled_lit_pass import lit_pass, lit_pass_applies
from ..model_components.compiled_march import GridDensity
from ..model_components.marcher import TRAIN_COLOURED_WEIGHT, TRAIN_RELATIVE_WEIGHT
from ..model_components.occupancy import cells_over
from ..field_components.grid_encodings import VectorMatrixGrid, Vertices
from ..field_components.grid_growth import cubic_vertices, grown_resolution, stage_of
from .base import MarchableField, SampleCost, VertexOccupancy, cell_corner_max
from .grid_appearance import GridAppearance


# How far the compiled cell pass's lower bound on the mean density must exceed the threshold for
# the mean to be left uncomputed: the bound's float sums are within 1e-5 of exact, and PyTorch's
# float mean within as little, so the rule's min(threshold, mean) is then the threshold.
MEAN_BOUND_SLACK = 1e-4


@dataclass(frozen=True)
class GridFieldConfig:
    # Grid vertices along the box's longest side at the end of training; the other sides get
    # as many as keep the cells cubic (vertices_at), or as many as the longest side when
    # cubic_cells is off (every axis alike, as before per-axis counts).
    resolution: int = 128
    cubic_cells: bool = True
    # Coarse-to-fine: start at initial_resolution and grow geometrically to `resolution`,
    # one step at each of upsample_iterations (cheap early steps, detail later).
    initial_resolution: int = 128
    upsample_iterations: tuple[int, ...] = ()
    # Under a time budget, the last growth (to `resolution`) waits for a run that can still take
    # this many steps at its rate so far: a finer grid needs steps to fill in, and with fewer the
    # grid stays one growth coarser (auto's rule, planning/rules.py). 0: it always grows.
    last_growth_min_steps: int = 0
    # Once the box is fitted to the scene (MarchedModel.fit_box), cells keep the count the
    # schedule gives over the box the field was built over, so they shrink with the box, but
    # never below this side (world units; auto: a training pixel's footprint). 0: no floor.
    finest_cell: float = 0.0
    density_channels: int = 16
    appearance_channels: int = 24
    appearance_dims: int = 27
    hidden_width: int = 64
    view_dependent: bool = True
    direction_frequencies: int = 2
    # Deferred colour (GridAppearance): the appearance features composited along each ray, the
    # colour network run once a ray rather than once a sample.
    deferred_colour: bool = False
    # Colour shaped by the scene's materials (GridAppearance.direction_inputs): with a dataset's
    # prior, samples in diffuse regions get no direction input, in metal ones the view reflected
    # about the true surface's normal (encoded with reflection_frequencies), elsewhere the view
    # as before. Without a prior (another tool's dataset) the same as without it.
    region_appearance: bool = False
    reflection_frequencies: int = 4
    # σ = density_scale · softplus(feature + density_shift): TensoRF's parametrisation.
    density_shift: float = -10.0
    density_scale: float = 25.0


class GridField(VertexOccupancy, GridAppearance, MarchableField):
    """``density(x [P,3]) -> [P]`` and ``colour(x [P,3], d [P,3]) -> [P,3]`` in world space.

    Points outside ``box`` read the grid's border values; callers sample inside the box.
    The occupancy grid's cells are the grid's cells.
    """

    SETTINGS_GROUP = "grid"
    Config = GridFieldConfig

    def __init__(self, config: GridFieldConfig, box: SceneBounds) -> None:
        super().__init__(box)
        self.config = config
        vertices = self.vertices_at(config.initial_resolution)
        self.density_grid = VectorMatrixGrid(config.density_channels, vertices)
        self.build_appearance(config, vertices)
        self.grown_to = config.initial_resolution  # the schedule's resolution the grids have now
        self._note: str | None = None
        self._held = False

    @property
    def resolution(self) -> int:
        """Vertices along the box's longest side."""
        return max(self.density_grid.vertices)

    @property
    def vertices(self) -> Vertices:
        return self.density_grid.vertices

    def resolution_after(self, iteration: int) -> int:
        """The schedule: the grid resolution once ``iteration`` steps have been taken."""
        config = self.config
        return grown_resolution(config.initial_resolution, config.resolution, config.upsample_iterations, iteration)

    def vertices_at(self, resolution: int) -> Vertices:
        """The vertices on each axis for the schedule's ``resolution``: that many along the
        longest side of the box the field was built over, with cubic cells; over a fitted box,
        as many cells as that gives over the built box, as cubes (not below ``finest_cell``)."""
        if not self.config.cubic_cells:
            return (resolution,) * 3
        return cubic_vertices(resolution, self.extent, self.built_extent, self.config.finest_cell)

    def fit_box(self, box: SceneBounds) -> bool:
        """Narrow both grids to ``box`` (inside the field's), resampled to the cells
        ``vertices_at`` gives there: a vector-matrix grid's part is read from its factors' parts."""
        if not self.config.cubic_cells:
            return False
        corners = self.normalise(torch.tensor([box.box_min, box.box_max], dtype=torch.float32,
                                              device=self.box_min.device)).tolist()
        self._set_box(box)
        vertices = self.vertices_at(self.grown_to)
        for grid in (self.density_grid, self.appearance_grid):
            grid.resize(vertices, tuple(corners[0]), tuple(corners[1]))
        return True

    def resize(self, vertices: Vertices) -> None:
        self.density_grid.resize(vertices)
        self.appearance_grid.resize(vertices)

    def density_from_features(self, summed: Tensor) -> Tensor:
        # float32 whatever precision autocast ran the products in: volume rendering needs it.
        return self.config.density_scale * F.softplus(summed.float() + self.config.density_shift)

    def density(self, x: Tensor) -> Tensor:
        return self.density_from_features(self.density_grid(self.normalise(x)).sum(dim=-1))

    def forward(self, x: Tensor, directions: Tensor, coloured: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Density and colour of the same points (colour only at ``coloured``, where given; with
        deferred colour, the appearance features instead: ``sample_appearance``),
        the grids read by the compiled kernel where it applies (training on the CPU:
        ``compiled_grid``; both grids in one pass when every point is coloured)."""
        normalised = self.normalise(x)
        if coloured is None:
            features = read_grids([self.density_grid, self.appearance_grid], normalised)
            if features is None:  # CUDA, MPS, no C compiler: PyTorch reads each grid
                density_features, appearance_features = self.density_grid(normalised), self.appearance_grid(normalised)
            else:
                density_features, appearance_features = features.split(
                    [self.density_grid.out_dims, self.appearance_grid.out_dims], dim=1)
            return (self.density_from_features(density_features.sum(dim=-1)),
                    self.sample_appearance(appearance_features, directions, x))
        density = self.density_from_features(self.density_grid(normalised).sum(dim=-1))
        shown = normalised.index_select(0, coloured)
        return density, self.sample_appearance(self.appearance_grid(shown), directions.index_select(0, coloured),
                                               x.index_select(0, coloured))

    def sample_cost(self) -> dict[str, SampleCost]:
        # Each channel of a component reads 4 plane and 2 line values, and interpolating
        # takes a multiply-add of each.
        density = 3 * (4 + 2) * self.config.density_channels
        costs = {"density": SampleCost(density, 2 * density), "colour": self.appearance_cost(),
                 "frozen density": SampleCost(8, 16)}  # one trilinear read of the density volume
        shade = self.shade_cost()
        return {**costs, "field": costs["density"] + costs["colour"], **({"shade": shade} if shade else {})}

    @torch.no_grad()
    def density_volume(self) -> Tensor:
        """The density's pre-activation at every vertex, ``[1, 1, Nz, Ny, Nx]`` laid out (z, y, x)
        for ``grid_sample``. Each grid component is bilinear × linear, i.e. trilinear, so a
        trilinear read of this volume equals the factorised grid's value: one 1-channel
        lookup instead of six many-channel ones (what inference uses)."""
        return self._dense_density()[None, None]

    def _dense_density(self) -> Tensor:
        """The density grid summed to a volume ``[Nz, Ny, Nx]``. Out of training, kept while the
        grid is unchanged: rendering reads it twice (the march's volume and the occupancy's
        vertex densities), 0.4 s each at 384 vertices a side; in training it would hold that
        memory between steps for nothing."""
        if self.training:
            return self.density_grid.dense_sum()
        return kept_derived(self, "dense sum", self.density_grid.parameters(), self.density_grid.dense_sum)

    def density_from_volume(self, volume: Tensor, x: Tensor, directions: Tensor | None = None) -> Tensor:
        """``density(x)`` read from ``density_volume()``'s result (the direction plays no part)."""
        grid = self.normalise(x).view(1, -1, 1, 1, 3)  # grid_sample's (x, y, z) = (W, H, D)
        summed = F.grid_sample(volume, grid, mode="bilinear", align_corners=True).view(-1)
        return self.density_from_features(summed)

    def compiled_density(self) -> GridDensity | None:
        """The density grid for the compiled training march (CPU, float32, a C compiler)."""
        found = density_components(self.density_grid)
        if found is None:
            return None
        return GridDensity(*found, scale=self.config.density_scale, shift=self.config.density_shift)

    def compiled_lit_pass(self) -> LitPassFn | None:
        """``MarchableField.compiled_lit_pass``: with deferred colour (not region-aware, whose
        samples carry direction inputs too), on the CPU in float32 with a C compiler."""
        if not self.deferred or self.region_aware or not lit_pass_applies(self.density_grid, self.appearance_grid):
            return None
        config, colouring = self.config, (TRAIN_COLOURED_WEIGHT, TRAIN_RELATIVE_WEIGHT)
        return lambda lit, weight, record, rays, steps: lit_pass(
            self.density_grid, self.appearance_grid, config.density_scale, config.density_shift, lit, weight, record,
            rays, steps, colouring)

    def volume_activation(self) -> tuple[str, float, float]:
        return "softplus", self.config.density_scale, self.config.density_shift

    @torch.no_grad()
    def occupancy_estimate(self) -> tuple[Tensor, float]:
        """``VertexOccupancy``'s cell maxima and mean density, in training computed in the dense
        sum's own memory: the same operations, each new volume-sized tensor fresh pages the kernel
        zeroes (lego's 205 × 355 × 227 cells: a refresh 293-393 ms, once in 67 steps, a tenth of
        the step)."""
        if not self.training:  # the dense sum is the cache rendering reads: leave it as it is
            return super().occupancy_estimate()
        density = self._activated_in_place(self._dense_density())  # [Nz, Ny, Nx], this call's own in training
        mean = float(density.mean())
        return cell_corner_max(density, overwrite=True).permute(2, 1, 0), mean

    @torch.no_grad()
    def cell_max_density(self) -> Tensor:
        """``VertexOccupancy``'s cell maxima for rendering, the maxima taken of the cached dense
        sum and only they activated: the activation (the shift, softplus, the scale) increases
        with the sum, so a cell's largest corner density is the activation of its largest corner
        sum. No vertex-sized density is made, and the sum rendering reads stays as it is."""
        cells = cell_corner_max(self._dense_density())  # [Nz-1, Ny-1, Nx-1], new
        return self._activated_in_place(cells).permute(2, 1, 0)

    @torch.no_grad()
    def occupied_cells(self, threshold: float, allowed: Tensor | None, rendering: bool) -> Tensor | None:
        """``MarchableField.occupied_cells`` in the dense sum's own terms, in one compiled pass
        (``occupancy.cells_over``): the density increases with the sum, so a cell's largest
        density exceeds a threshold where its largest corner sum exceeds ``_sum_above`` of it.
        The mean density is computed only where the pass's bound under it (softplus(v) >
        max(0, v)) does not already exceed the threshold: a young, faint field. Lego's
        thirty-minute grid (309 × 532 × 344 vertices, rendering, 2 cores): 0.54-0.78 s through
        PyTorch, 0.09-0.11 s so."""
        if self.density_grid.planes[0].device.type != "cpu":
            return super().occupied_cells(threshold, allowed, rendering)
        sums = self._dense_density()  # [Nz, Ny, Nx]: fresh in training, kept while rendering
        shift, scale = self.config.density_shift, self.config.density_scale
        marked = cells_over(sums, self._sum_above(threshold), shift, allowed)
        if marked is None:  # no compiler: through PyTorch (the sum made again in training)
            return super().occupied_cells(threshold, allowed, rendering)
        occupied, vertex_excess, cell_excess = marked
        excess, count = (cell_excess, occupied.numel()) if rendering else (vertex_excess, sums.numel())
        if scale * excess / count >= threshold * (1.0 + MEAN_BOUND_SLACK):
            return occupied
        # The rule's own mean: of the cells' largest densities, or over the vertices.
        mean = float((self.cell_max_density() if rendering else self.density_from_features(sums)).mean())
        if mean >= threshold:
            return occupied
        return cells_over(sums, self._sum_above(mean), shift, allowed)[0]

    def _sum_above(self, density: float) -> float:
        """The pre-activation sum ``v`` whose density ``scale · softplus(v + shift)`` is
        ``density`` (the density exceeds it exactly where the sum exceeds this); −∞ for a
        density ≤ 0, which every sum's exceeds."""
        y = density / self.config.density_scale
        if not y > 0.0:
            return -math.inf
        return y + math.log(-math.expm1(-y)) - self.config.density_shift  # softplus⁻¹(y), stable for all y > 0

    def _activated_in_place(self, summed: Tensor) -> Tensor:
        """``density_from_features`` of a float32 sum no gradient flows through, in its own memory."""
        summed.add_(self.config.density_shift)
        torch.ops.aten.softplus.out(summed, 1.0, 20.0, out=summed)  # F.softplus's beta and threshold
        return summed.mul_(self.config.density_scale)

    @torch.no_grad()
    def vertex_density(self) -> Tensor:
        """Density at every grid vertex ``[Nx, Ny, Nz]``: within each grid cell the
        density's pre-activation is trilinear, so these bound the density in the cell."""
        return self.density_from_features(self._dense_density().permute(2, 1, 0))

    def encoding_parameters(self) -> list[nn.Parameter]:
        return [*self.density_grid.parameters(), *self.appearance_grid.parameters()]

    def coarse_detail(self) -> float | None:
        """The cell's shortest side while the grid is coarser than its final resolution."""
        if self.grown_to >= self.config.resolution:
            return None
        return min(side / cells for side, cells in zip(self.extent, self.occupancy_cells()))

    def before_step(self, scheduled: int, steps_left: float | None = None) -> bool:
        """Upsample on schedule (coarse-to-fine); the last growth only with
        ``last_growth_min_steps`` left in the budget."""
        resolution = self.resolution_after(scheduled)
        if resolution == self.grown_to:
            return False
        if resolution == self.config.resolution and not self._worth_growing(steps_left):
            return False
        self.resize(self.vertices_at(resolution))
        self.grown_to = resolution
        return True

    def _worth_growing(self, steps_left: float | None) -> bool:
        """Whether the budget leaves the final grid the steps it needs (said once when not)."""
        wanted = self.config.last_growth_min_steps
        if wanted <= 0 or steps_left is None or steps_left >= wanted:
            return True
        if not self._held:
            self._held = True
            self._note = (f"grid kept at {self.resolution} vertices a side, not grown to {self.config.resolution}: "
                          f"about {steps_left:.0f} steps are left in the time budget, and the last growth waits "
                          f"for {wanted} (grid.last_growth_min_steps)")
        return False

    def take_note(self) -> str | None:
        note, self._note = self._note, None
        return note

    def match_state(self, state: dict[str, Tensor]) -> bool:
        """Take the box and vertices a checkpoint was saved with (also cubic grids from before
        each axis had its own count), and the schedule's resolution they stand for."""
        changed = self._take_box(state)
        self.match_surface_facts(state)
        (nx, ny), nz = state["density_grid.planes.0"].shape[-2:], state["density_grid.planes.1"].shape[-1]
        if (nx, ny, nz) != self.vertices:
            self.resize((nx, ny, nz))
            changed = True
        config = self.config
        self.grown_to = stage_of(config.initial_resolution, config.resolution, config.upsample_iterations,
                                 self.vertices_at, self.vertices)
        return changed
