"""What a marched model asks of its field: density and colour at world points over the
scene's box, and an estimate of where density is, for the occupancy grid. A new field that
implements these, names its settings (``SETTINGS_GROUP``, a ``Config`` dataclass) and has an
entry in ``models/registry.py`` (``MarchedModel.of(TheField)``) is marched, trained, rendered
and benched with no other change."""

from __future__ import annotations

from typing import Callable, NamedTuple

import torch
from torch import Tensor, nn

from ..core.field_functions import LitPassFn, RayColourFn, ShadeFn
from ..core.scene_bounds import SceneBounds
from ..model_components.occupancy import cells_exceeding


class SampleCost(NamedTuple):
    """What evaluating one sample costs: values gathered from memory (grid or table reads)
    and floating-point operations (a multiply-add is 2)."""

    gathers: int
    flops: int

    def __add__(self, other: "SampleCost") -> "SampleCost":  # type: ignore[override]
        return SampleCost(self.gathers + other.gathers, self.flops + other.flops)


def mlp_flops(network: nn.Module) -> int:
    """FLOPs of one input through every ``nn.Linear`` of ``network`` (2 per weight)."""
    return sum(2 * m.in_features * m.out_features for m in network.modules() if isinstance(m, nn.Linear))


def cell_corner_max(vertex_values: Tensor, overwrite: bool = False) -> Tensor:
    """The largest of each cell's 8 corner values: ``[Nx, Ny, Nz]`` vertices → ``[Nx-1, Ny-1, Nz-1]``
    cells, one axis at a time (max_pool3d's 2×2×2 window took 376 ms at 256³ on 2 CPU cores;
    three elementwise maxima, a few ms). ``overwrite``: the values are not needed after, and
    where contiguous the second maximum is written into their memory and the third into the
    first's, one new tensor instead of three (a new volume-sized tensor is fresh pages the
    kernel zeroes: at lego's 206 × 356 × 229 vertices a maximum into a new tensor took 28 ms,
    into one that exists 3-8 ms).

    Example:
        >>> cell_corner_max(torch.arange(8.0).view(2, 2, 2)).tolist()
        [[[7.0]]]
        >>> cell_corner_max(torch.arange(27.0).view(3, 3, 3), overwrite=True).tolist()
        [[[13.0, 14.0], [16.0, 17.0]], [[22.0, 23.0], [25.0, 26.0]]]
    """
    a, b, c = vertex_values.shape
    reuse = overwrite and vertex_values.is_contiguous()
    first = torch.maximum(vertex_values[:-1], vertex_values[1:])  # new, contiguous
    into = vertex_values.view(-1)[:(a - 1) * (b - 1) * c].view(a - 1, b - 1, c) if reuse else None
    second = torch.maximum(first[:, :-1], first[:, 1:], out=into)
    into = first.view(-1)[:(a - 1) * (b - 1) * (c - 1)].view(a - 1, b - 1, c - 1) if reuse else None
    return torch.maximum(second[:, :, :-1], second[:, :, 1:], out=into)


class MarchableField(nn.Module):
    """``density(x [P,3]) -> [P]`` and ``colour(x [P,3], d [P,3]) -> [P,3]`` in world space,
    over ``box`` (points outside it are never asked for). Built as ``Field(config, box)``
    (``Field(config, box, prior)`` where ``STARTS_FROM_PRIOR``)."""

    # The field's settings: their group's name in a run's config, presets.json and --set
    # (``grid.resolution=96``), and the frozen dataclass holding them.
    SETTINGS_GROUP: str = ""
    Config: type = object
    # Rays per inference pass when rendering whole images, where the marched models' default
    # does not suit the field (None: the default).
    render_chunk: int | None = None
    # Whether the field is built from the dataset's occupancy prior as well
    # (``Field(config, box, prior)``): the surface field starts its distance from it.
    STARTS_FROM_PRIOR: bool = False
    # The backward pass's work over the forward's, for bench-step's reference: the gradient of a
    # product reads its other factors again and writes the gradients (2: the factorised grids,
    # the networks); a trilinear blend's gradient needs only its weights (1: a voxel grid).
    BACKWARD_WORK: int = 2
    # The march's step (world units), set by the model whenever its sampling follows the field:
    # a density over a step (``density_along``) may need it.
    march_step: float = 0.0

    def __init__(self, box: SceneBounds) -> None:
        super().__init__()
        self.register_buffer("box_min", torch.tensor(box.box_min, dtype=torch.float32))
        self.register_buffer("box_max", torch.tensor(box.box_max, dtype=torch.float32))
        self.extent = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))
        self.built_extent = self.extent  # the box it was built over, before any fitting

    @property
    def box(self) -> SceneBounds:
        return SceneBounds(tuple(self.box_min.tolist()), tuple(self.box_max.tolist()))  # type: ignore[arg-type]

    def _set_box(self, box: SceneBounds) -> None:
        self.box_min.copy_(torch.tensor(box.box_min, dtype=torch.float32))
        self.box_max.copy_(torch.tensor(box.box_max, dtype=torch.float32))
        self.extent = tuple(hi - lo for lo, hi in zip(box.box_min, box.box_max))

    def _take_box(self, state: dict[str, Tensor]) -> bool:
        """Take the box a checkpoint's ``state`` was saved with; True when it changed."""
        box = SceneBounds(tuple(state["box_min"].tolist()), tuple(state["box_max"].tolist()))  # type: ignore[arg-type]
        if box == self.box:
            return False
        self._set_box(box)
        return True

    def fit_box(self, box: SceneBounds) -> bool:
        """Narrow the field to ``box`` (inside its own), keeping what it holds there; False
        where the field cannot (it stays over its whole box)."""
        return False

    def normalise(self, x: Tensor) -> Tensor:
        """World points → [-1, 1] over the box."""
        return (x - self.box_min) / (self.box_max - self.box_min) * 2.0 - 1.0

    def density(self, x: Tensor) -> Tensor:
        raise NotImplementedError

    def colour(self, x: Tensor, directions: Tensor) -> Tensor:
        raise NotImplementedError

    def density_along(self, x: Tensor, directions: Tensor) -> Tensor:
        """The density marchers use for a sample at ``x`` of a ray along ``directions``: the
        field's ``density(x)``, unless its opacity depends on the way a ray crosses it (the
        surface field's NeuS opacity)."""
        return self.density(x)

    def ray_colour(self, directions: Tensor, dtype: torch.dtype = torch.float32) -> RayColourFn:
        """``colour`` for samples packed from rays of these ``directions [R, 3]`` (inference's
        marchers): a function of the samples' points ``[P, 3]`` and rays ``[P]`` (indices into
        ``directions``). A field whose colour does work that is the same along a ray does it
        once a ray here; one whose colour is a network may run its products in ``dtype``
        (``devices.colour_network_dtype``)."""
        return lambda x, ray: self.colour(x, directions.index_select(0, ray))

    def shade_fn(self) -> ShadeFn | None:
        """Deferred colour: where marched samples carry appearance features (``forward``'s second
        output, ``ray_features``) rather than colours, the function giving a ray its colour
        from their weighted mean (``volume_rendering.shade_rays``); None where they carry colours."""
        return None

    def ray_features(self, directions: Tensor) -> RayColourFn:
        """With deferred colour, ``ray_colour``'s counterpart giving packed samples' appearance
        features ``[P, C]`` for ``shade_fn``."""
        raise NotImplementedError(f"{type(self).__name__} has no deferred colour")

    def forward(self, x: Tensor, directions: Tensor, coloured: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Density and colour of the same points in one call (a field that shares work
        between them overrides this); with ``coloured`` (indices into the points), colour only
        there (``SparseColourFieldFn``)."""
        if coloured is None:
            return self.density_along(x, directions), self.colour(x, directions)
        return self.density_along(x, directions), self.colour(x[coloured], directions[coloured])

    def occupancy_cells(self) -> tuple[int, int, int]:
        """Cells per axis of the occupancy grid over the box (the march's step follows them)."""
        raise NotImplementedError

    def occupancy_estimate(self) -> tuple[Tensor, float]:
        """The largest density in each occupancy cell ``[Gx, Gy, Gz]`` (an exact bound where
        the field allows one, else an estimate) and the field's mean density; training calls
        it on the occupancy grid's schedule (an estimate may move with each call)."""
        raise NotImplementedError

    def cell_max_density(self) -> Tensor | None:
        """``occupancy_estimate``'s cell maxima as they stand, changing nothing (what
        rendering prunes its grid with); None before the field has any."""
        raise NotImplementedError

    @torch.no_grad()
    def occupied_cells(self, threshold: float, allowed: Tensor | None, rendering: bool) -> Tensor | None:
        """Bool ``[Gx, Gy, Gz]``: the cells whose largest density exceeds ``threshold``, or the
        mean density where that is lower (Instant-NGP's rule: a young, faint field is never
        pruned to nothing), and only ``allowed`` ones where given. In training (``rendering``
        False) from a fresh ``occupancy_estimate`` and the field's mean density; for rendering
        from ``cell_max_density`` as it stands and the mean of the cells' maxima (nerfacc's
        rule), None before the field has any."""
        if rendering:
            cell_max = self.cell_max_density()
            if cell_max is None:
                return None
            mean = float(cell_max.mean())
        else:
            cell_max, mean = self.occupancy_estimate()
        return cells_exceeding(cell_max, min(threshold, mean), allowed)

    def sample_cost(self) -> dict[str, SampleCost]:
        """One sample's cost in each of the field's reads: ``"density"``, ``"colour"``,
        ``"field"`` (``forward``: both) and ``"frozen density"`` (``density_from_volume``);
        with deferred colour also ``"shade"``, the network's once a shaded ray.
        bench-step states the field's stages
        against the CPU's measured gather and FLOP rates with these."""
        raise NotImplementedError

    def density_volume(self) -> Tensor | None:
        """A precomputed form of the density for fast reads without gradients, or None."""
        return None

    def density_from_volume(self, volume: Tensor | None, x: Tensor, directions: Tensor | None = None) -> Tensor:
        """``density_along(x, directions)`` (``density(x)`` without directions) read from
        ``density_volume()``'s result."""
        return self.density(x) if directions is None else self.density_along(x, directions)

    def compiled_density(self):
        """The field's density as the compiled training march reads it
        (``compiled_march.GridDensity``), or None where it has no such form (then the march runs
        through PyTorch)."""
        return None

    def compiled_lit_pass(self) -> LitPassFn | None:
        """With deferred colour, the field's training pass over the compiled march's lit samples
        and their records in one call (``LitPassFn``), or None (then ``forward`` and the
        compositing run through PyTorch)."""
        return None

    def volume_activation(self) -> tuple[str, float, float] | None:
        """How ``density_from_volume`` turns the volume's trilinear value into density, as
        ``(activation, scale, shift)`` of ``compiled_march.VolumeDensity``, so the compiled
        march can read it; None where the density is not such a read."""
        return None

    def surface_function(self) -> Callable[[Tensor], Tensor] | None:
        """``Model.surface_function``: positive inside, zero on the surface; None when the
        surface is a level of the density."""
        return None

    def regularisation(self, generator: torch.Generator | None = None) -> Tensor | None:
        """``Model.regularisation``: the field's own loss terms at a training step, or None."""
        return None

    def encoding_parameters(self) -> list[nn.Parameter]:
        """Parameters of the spatial encoding (grids, hash tables): the optimiser gives them
        the encoding learning rate, every other parameter the network one."""
        return []

    def coarse_detail(self) -> float | None:
        """While the field grows toward finer detail on its schedule: the size (world units)
        of the finest detail it holds now (what coarse-to-fine training downsamples the
        images to); None once it holds its final detail, or if it never grows."""
        return None

    def before_step(self, scheduled: int, steps_left: float | None = None) -> bool:
        """Schedules of the field's own (a grid's upsampling), at ``scheduled`` steps into
        the run's schedule, ``steps_left`` the steps a time budget still allows
        (``Model.before_step``). True when the parameters were replaced, so the optimiser and
        the occupancy grid must follow."""
        return False

    def after_step(self) -> None:
        """After each optimiser step (``Model.after_step``): constraints the field keeps by
        projection (the surface field's bounds from Blender's prior)."""

    def take_note(self) -> str | None:
        """What the field's schedule decided that the user should hear (once), or None."""
        return None

    def match_state(self, state: dict[str, Tensor]) -> bool:
        """Take the shapes a checkpoint's ``state`` (this field's entries) was saved with.
        True when the field changed shape."""
        return False


class VertexOccupancy:
    """Mixed into a ``MarchableField`` whose density is a monotone activation of a value
    trilinear in each grid cell (the grid and Plenoxels fields): the occupancy grid's cells are
    the grid's, and a cell's largest density is its largest corner's, exactly. The field gives
    ``vertices`` and ``vertex_density()`` (``[Nx, Ny, Nz]``)."""

    def occupancy_cells(self) -> tuple[int, int, int]:
        return tuple(n - 1 for n in self.vertices)  # type: ignore[attr-defined, return-value]

    @torch.no_grad()
    def occupancy_estimate(self) -> tuple[Tensor, float]:
        density = self.vertex_density()  # type: ignore[attr-defined]
        return cell_corner_max(density), float(density.mean())

    @torch.no_grad()
    def cell_max_density(self) -> Tensor:
        return cell_corner_max(self.vertex_density())  # type: ignore[attr-defined]
