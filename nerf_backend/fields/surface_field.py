"""The surface field: a signed distance function whose zero level set is the scene's surface,
rendered as a density (VolSDF) and marched like every other field.

The signed distance ``s`` (negative inside) lives in a dense grid (``DenseGrid``, Voxurf's
choice: a factorised grid's low rank rounds a surface off); the density is VolSDF's

    σ(x) = Ψ_β(−s(x)) / β,   Ψ_β the Laplace distribution's CDF with scale β,

so density is ``1/β`` inside, ``1/(2β)`` on the surface and falls off as ``exp(−s/β)``
outside; β, the surface's softness, is learnt (VolSDF), never below ``min_beta_cells`` of a
cell. An eikonal term keeps ``|∇s| = 1`` (finite differences between grid vertices: a grid
read has no second derivative to back-propagate). Colour is the grid field's
(``GridAppearance``). The grid starts as the signed distance to Blender's solid occupancy
prior where the dataset has one (the surface within about a prior cell from the start), else
as a sphere. With that prior the distance is kept, after every step, within the bounds it gives
(``surface_band.py``: the surface lies in the prior's surface cells less their margin), so the
images choose the surface within about a prior cell of Blender's own.

Example:
    >>> from ..core.scene_bounds import SceneBounds
    >>> field = SurfaceField(SurfaceFieldConfig(resolution=33, initial_resolution=33), SceneBounds((-1,) * 3, (1,) * 3))
    >>> sdf = field.signed_distance(torch.tensor([[0.0, 0.0, 0.0], [0.75, 0.0, 0.0]]))
    >>> [round(v, 3) for v in sdf.tolist()]  # the starting sphere of radius 0.5
    [-0.5, 0.25]
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..core.errors import NerfError
from ..core.field_functions import RayColourFn
from ..core.scene_bounds import SceneBounds, vertices_for
from ..data.occupancy_prior import OccupancyPrior
from ..field_components.dense_grid import DenseGrid, Vertices
from ..field_components.distance_transform import distance_to_unset
from ..field_components.grid_growth import grown_resolution
from ..field_components.surface_band import SignedDistanceBounds
from .base import MarchableField, SampleCost, cell_corner_max
from .grid_appearance import GridAppearance

OPACITIES = ("volsdf", "neus")


@dataclass(frozen=True)
class SurfaceFieldConfig:
    # Vertices of the signed-distance grid along the box's longest side at the end (cubic
    # cells), grown from initial_resolution at each of upsample_iterations.
    resolution: int = 192
    initial_resolution: int = 64
    upsample_iterations: tuple[int, ...] = ()
    # VolSDF's β (the surface's softness): from initial_beta_cells of the grid's first cell
    # to final_beta_cells of its last, geometrically, over beta_iterations of the schedule
    # (a soft surface early lets the images move it; a sharp one late puts it in place).
    # Measured, 120 s on the 100×100 suite's A and demo: a final 0.5 cell scored 30.72 and
    # 31.00 dB where 0.2 scored 27.27 and 29.31 (its PSNR fell as β sharpened), at the same
    # F-score (0.684 / 0.757 against 0.688 / 0.757).
    initial_beta_cells: float = 1.0
    final_beta_cells: float = 0.5
    beta_iterations: int = 2000
    # How a ray's opacity follows the distance: "volsdf", the density Ψ_β(−s)/β of each point;
    # "neus", NeuS's opacity of each step, from the distance where the ray enters and leaves it
    # (1 − Φ(s_out)/Φ(s_in), Φ the logistic of s/β, none where the distance grows). VolSDF's
    # density outside the surface piles up along rays that graze it, so its silhouettes lie
    # outside the zero level and training pulls the surface inward (A.blend at 800×800: a cell
    # inside the truth); NeuS's transmittance halves exactly at the zero level. The surface
    # preset chooses NeuS where Blender's prior bounds the surface (planning/rules.py, surface_opacity).
    opacity: str = "volsdf"
    # Keep the distance within the bounds Blender's occupancy prior gives (surface_band.py:
    # the surface lies in the prior's surface cells less their margin), by projection after
    # every step, where the dataset has a solid prior with its surface cells.
    prior_band: bool = True
    # The eikonal term's weight in the loss and the grid vertices it is taken at a step.
    eikonal_weight: float = 0.1
    eikonal_vertices: int = 16384
    # Without a prior: a sphere of this fraction of the box's smallest half-side.
    initial_radius: float = 0.5
    # Colour sees the surface's normal, and the viewing direction reflected about it
    # (Ref-NeRF's reflection direction: a mirror's colour is a function of it alone). Off:
    # on the 100×100 demo, 3000 steps, both on gave 30.46 dB against 30.33 and F-score 0.809
    # against 0.819, for 6 more distance reads a coloured sample.
    normal_input: bool = False
    reflected_directions: bool = False
    appearance_channels: int = 24
    appearance_dims: int = 27
    hidden_width: int = 64
    view_dependent: bool = True
    direction_frequencies: int = 2


class SurfaceField(GridAppearance, MarchableField):
    """``signed_distance(x)``, ``density(x)`` (VolSDF's) and ``colour(x, d)`` in world space."""

    SETTINGS_GROUP = "surface"
    Config = SurfaceFieldConfig
    STARTS_FROM_PRIOR = True

    def __init__(self, config: SurfaceFieldConfig, box: SceneBounds, prior: OccupancyPrior | None = None) -> None:
        super().__init__(box)
        if config.opacity not in OPACITIES:
            raise NerfError(f"surface.opacity {config.opacity!r}: choose {' or '.join(OPACITIES)}")
        self.config = config
        vertices = vertices_for(config.initial_resolution, self.extent)
        final_cell = min(self._cell_sides(vertices_for(config.resolution, self.extent)))
        # Distances are held in final cells: an encoding step of 0.02 moves one by 0.02 cells.
        self.sdf_grid = DenseGrid(self._initial_distance(vertices, prior), unit=final_cell)
        self.build_appearance(config, vertices, extra_inputs=3 if config.normal_input else 0)
        self.initial_beta = config.initial_beta_cells * min(self._cell_sides(vertices))
        self.final_beta = config.final_beta_cells * final_cell
        # A buffer: a checkpoint renders with the softness it was trained to.
        self.register_buffer("beta", torch.tensor(self.initial_beta))
        # The band's bounds are built at the first step (training only: two distance transforms
        # of the prior, 0.3-0.5 s each at 256 cells a side) and fitted to the vertices at each size.
        self._band_prior = prior if config.prior_band and prior is not None and prior.bounds_the_surface else None
        self.band: SignedDistanceBounds | None = None
        self.register_buffer("vertex_lower", None, persistent=False)
        self.register_buffer("vertex_upper", None, persistent=False)
        self._note: str | None = None
        if self._band_prior is not None:
            self._note = (f"the surface is kept within the band Blender's geometry marks (occupancy prior cells of "
                          f"{self._band_prior.cell_size:.4g}, less their margin of {self._band_prior.margin_cells}; "
                          f"surface.prior_band)")

    # --- the signed distance and its density -------------------------------------------------

    def _cell_sides(self, vertices: Vertices) -> tuple[float, float, float]:
        return tuple(side / (n - 1) for side, n in zip(self.extent, vertices))  # type: ignore[return-value]

    def _vertex_positions(self, vertices: Vertices) -> list[Tensor]:
        return [torch.linspace(lo, hi, n, dtype=torch.float64)
                for lo, hi, n in zip(self.box_min.tolist(), self.box_max.tolist(), vertices)]

    def _initial_distance(self, vertices: Vertices, prior: OccupancyPrior | None) -> Tensor:
        """``[Nx, Ny, Nz]``: the signed distance to the surface the prior's solid cells imply, or
        to a sphere at the box's centre without a prior (or with one that marks no cell, or
        every cell: no surface to start from)."""
        axes = self._vertex_positions(vertices)
        if prior is None or not bool(prior.occupied.any()) or bool(prior.occupied.all()):
            centre = [(lo + hi) / 2 for lo, hi in zip(self.box_min.tolist(), self.box_max.tolist())]
            points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
            radius = self.config.initial_radius * min(self.extent) / 2
            return ((points - torch.tensor(centre, dtype=torch.float64)).norm(dim=-1) - radius).float()
        return self._prior_distance(prior, axes)

    @staticmethod
    def _prior_distance(prior: OccupancyPrior, axes: list[Tensor]) -> Tensor:
        """The signed distance to the surface the prior's solid cells imply, at the vertices on
        ``axes``: at each prior cell's centre the distance to the nearest cell of the other kind
        less half a cell (the marked region's boundary), moved in by the margin the cells were
        grown by and half a cell more (where the surface lies within its marked cells), then
        read trilinearly at the vertices."""
        inside = prior.occupied.numpy()
        outside_distance = distance_to_unset(~inside)
        inside_distance = distance_to_unset(inside)
        cells = np.where(inside, 0.5 - inside_distance, outside_distance - 0.5) + prior.margin_cells + 0.5
        volume = torch.from_numpy((cells * prior.cell_size).astype(np.float32)).permute(2, 1, 0)[None, None]
        # Vertices in the prior's normalised coordinates (-1 and 1: its first and last cell centres).
        normalised = [(axis - lo - prior.cell_size / 2) / (prior.cell_size * (n - 1)) * 2 - 1
                      for axis, lo, n in zip(axes, prior.box_min, prior.occupied.shape)]
        grid = torch.stack(torch.meshgrid(*normalised, indexing="ij"), dim=-1).float()
        distance = F.grid_sample(volume, grid.view(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border",
                                 align_corners=True)
        return distance.view(grid.shape[:3])

    @torch.no_grad()
    def _fit_band(self) -> None:
        """The band's bounds at the grid's vertices, in the grid's units and layout."""
        prior = self._band_prior
        assert prior is not None and prior.surface_cells is not None
        device = self.sdf_grid.values.device
        if self.band is None:
            self.band = SignedDistanceBounds(prior.surface_cells.numpy(), prior.occupied.numpy(), prior.box_min,
                                             prior.cell_size, prior.margin_cells).to(device)
        band = self.band
        axes = [axis.float().to(device) for axis in self._vertex_positions(self.vertices)]  # MPS has no float64
        points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)
        lower, upper = band(points.view(-1, 3))
        unit = self.sdf_grid.unit
        for name, bound in (("vertex_lower", lower), ("vertex_upper", upper)):
            layout = (bound.view(points.shape[:3]) / unit).permute(2, 1, 0).contiguous()[None, None]
            self.register_buffer(name, layout, persistent=False)  # [1, 1, Nz, Ny, Nx], as the grid

    @torch.no_grad()
    def after_step(self) -> None:
        """Project the distances onto the band's bounds (a clamp of the grid: about 1 ms
        for 192³ vertices on 2 CPU cores)."""
        if self._band_prior is None:
            return
        values = self.sdf_grid.values
        if self.vertex_lower is None or self.vertex_lower.shape != values.shape:
            self._fit_band()
        torch.maximum(torch.minimum(values, self.vertex_upper), self.vertex_lower, out=values.data)

    def take_note(self) -> str | None:
        note, self._note = self._note, None
        return note

    def beta_after(self, scheduled: int) -> float:
        """β once ``scheduled`` steps of the schedule have been taken."""
        done = min(1.0, scheduled / max(1, self.config.beta_iterations))
        return self.initial_beta * (self.final_beta / self.initial_beta) ** done

    def signed_distance(self, x: Tensor) -> Tensor:
        return self.sdf_grid(self.normalise(x))

    def density_from_distance(self, distance: Tensor) -> Tensor:
        """VolSDF: ``Ψ_β(−s) / β``, in float32 whatever precision the rest runs in."""
        beta = self.beta
        s = distance.float()
        tail = 0.5 * torch.exp(-s.abs() / beta)
        return torch.where(s > 0, tail, 1.0 - tail) / beta

    def density(self, x: Tensor) -> Tensor:
        return self.density_from_distance(self.signed_distance(x))

    def density_along(self, x: Tensor, directions: Tensor) -> Tensor:
        if self.config.opacity != "neus":
            return self.density(x)
        return self._step_density(lambda points: self.signed_distance(points), x, directions)

    def _step_density(self, distance_at: Callable[[Tensor], Tensor], x: Tensor, directions: Tensor) -> Tensor:
        """NeuS's opacity of the march step centred on ``x``, as the density that gives it over
        the step: ``−ln(Φ(s_out)/Φ(s_in)) / step``, 0 where the distance grows along the ray."""
        step = self.march_step
        half = directions * (0.5 * step)
        distance = distance_at(torch.cat([x - half, x + half])).float().view(2, -1)
        beta = self.beta
        # ln Φ(s) = −softplus(−s/β): the difference of two such, stable at any distance.
        optical = F.softplus(-distance[1] / beta) - F.softplus(-distance[0] / beta)
        return optical.clamp_min(0.0) / step

    def density_bound_from_distance(self, distance: Tensor) -> Tensor:
        """The largest density a point at ``distance`` can have, for the occupancy grid: VolSDF's
        density, or for NeuS's opacity (|∇s| ≈ 1, a step's entry and exit a step apart) the
        logistic's slope bound σ(−s/β)/β."""
        if self.config.opacity != "neus":
            return self.density_from_distance(distance)
        return torch.sigmoid(-distance.float() / self.beta) / self.beta

    def normals(self, x: Tensor) -> Tensor:
        """The distance's unit gradient at ``x``: central differences half a cell apart (a grid
        read has no second derivative; these carry the images' gradient to the distances)."""
        sides = self._cell_sides(self.vertices)
        offsets = torch.diag(torch.tensor([side / 2 for side in sides], dtype=x.dtype, device=x.device))
        points = torch.cat([x[:, None, :] + offsets, x[:, None, :] - offsets], dim=1).view(-1, 3)
        distance = self.signed_distance(points).view(-1, 2, 3)
        return torch.nn.functional.normalize(distance[:, 0] - distance[:, 1], dim=-1)

    def colour(self, x: Tensor, directions: Tensor) -> Tensor:
        config = self.config
        if not (config.normal_input or config.reflected_directions):
            return self.colour_with(x, directions)
        normal = self.normals(x)
        if config.reflected_directions:
            directions = directions - 2 * (directions * normal).sum(dim=-1, keepdim=True) * normal
        return self.colour_with(x, directions, normal if config.normal_input else None)

    def ray_colour(self, directions: Tensor, dtype: torch.dtype = torch.float32) -> RayColourFn:
        if self.config.normal_input or self.config.reflected_directions:
            return MarchableField.ray_colour(self, directions)  # the direction depends on each sample's normal
        return super().ray_colour(directions, dtype)

    def surface_function(self) -> Callable[[Tensor], Tensor]:
        """``-signed_distance``: the mesh is the distance's zero level set."""
        return lambda x: -self.signed_distance(x)

    # --- the eikonal term ------------------------------------------------------------------------

    def regularisation(self, generator: torch.Generator | None = None) -> Tensor:
        """``eikonal_weight · mean((|∇s| − 1)²)`` at random vertices, ``∇s`` by forward
        differences to the next vertex on each axis."""
        values = self.sdf_grid.vertex_values()
        device = values.device
        count = self.config.eikonal_vertices
        index = [torch.randint(0, n - 1, (count,), generator=generator, device=device) for n in values.shape]
        at = values[index[0], index[1], index[2]]
        sides = self._cell_sides(self.vertices)
        gradient = torch.stack([
            (values[index[0] + 1, index[1], index[2]] - at) / sides[0],
            (values[index[0], index[1] + 1, index[2]] - at) / sides[1],
            (values[index[0], index[1], index[2] + 1] - at) / sides[2]], dim=-1)
        return self.config.eikonal_weight * (gradient.norm(dim=-1) - 1.0).square().mean()

    # --- the march's needs ---------------------------------------------------------------------

    @property
    def vertices(self) -> Vertices:
        return self.sdf_grid.vertices

    @property
    def resolution(self) -> int:
        return max(self.vertices)

    def occupancy_cells(self) -> Vertices:
        return tuple(n - 1 for n in self.vertices)  # type: ignore[return-value]

    @torch.no_grad()
    def cell_max_density(self) -> Tensor:
        """Each cell's largest density, exactly: the distance is trilinear within a cell, so
        its least value is at a corner, and density falls as distance grows."""
        return cell_corner_max(self.density_bound_from_distance(self.sdf_grid.vertex_values()))

    @torch.no_grad()
    def occupancy_estimate(self) -> tuple[Tensor, float]:
        return self.cell_max_density(), float(self.density_bound_from_distance(self.sdf_grid.vertex_values()).mean())

    def sample_cost(self) -> dict[str, SampleCost]:
        reads = 2 if self.config.opacity == "neus" else 1  # NeuS reads the distance where a step begins and ends
        density = SampleCost(8 * reads, 16 * reads + 8)  # trilinear reads, then the activation
        return {"density": density, "colour": self.appearance_cost(), "frozen density": density,
                "field": density + self.appearance_cost()}

    def density_volume(self) -> Tensor:
        return self.sdf_grid.values.detach() * self.sdf_grid.unit

    def density_from_volume(self, volume: Tensor, x: Tensor, directions: Tensor | None = None) -> Tensor:
        def distance_at(points: Tensor) -> Tensor:
            return DenseGrid.read(volume, self.normalise(points))

        if self.config.opacity == "neus" and directions is not None:
            return self._step_density(distance_at, x, directions)
        return self.density_from_distance(distance_at(x))

    def volume_activation(self) -> tuple[str, float, float]:
        return ("neus" if self.config.opacity == "neus" else "laplace"), float(self.beta), 0.0

    def encoding_parameters(self) -> list[nn.Parameter]:
        return [*self.sdf_grid.parameters(), *self.appearance_grid.parameters()]

    # --- growth --------------------------------------------------------------------------------

    def resize(self, vertices: Vertices) -> None:
        self.sdf_grid.resize(vertices)
        self.appearance_grid.resize(vertices)

    def coarse_detail(self) -> float | None:
        if self.resolution >= self.config.resolution:
            return None
        return min(self._cell_sides(self.vertices))

    def before_step(self, scheduled: int, steps_left: float | None = None) -> bool:
        """β on its schedule, and the grids' growth."""
        self.beta.fill_(self.beta_after(scheduled))
        config = self.config
        resolution = grown_resolution(config.initial_resolution, config.resolution, config.upsample_iterations,
                                      scheduled)
        if resolution == self.resolution:
            return False
        self.resize(vertices_for(resolution, self.extent))
        return True

    def match_state(self, state: dict[str, Tensor]) -> bool:
        nz, ny, nx = state["sdf_grid.values"].shape[-3:]
        if (nx, ny, nz) == self.vertices:
            return False
        self.resize((nx, ny, nz))
        return True
