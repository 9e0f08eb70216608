"""Models that march a ``MarchableField`` in fixed steps through the scene's box, skipping
cells an occupancy grid knows are empty and computing colour only for samples light reaches.
The field decides everything field-specific (its cells, its density estimate, its schedule);
the march is ``model_components.marcher``'s, the same for every field."""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator, NamedTuple

import torch
from torch import Tensor

from ..core.cameras import ray_box_intersection
from ..core.devices import colour_network_dtype
from ..core.scene_bounds import SceneBounds
from ..core.tensor_keys import kept_derived
from ..data.occupancy_prior import OccupancyPrior
from ..field_components.environment import Environment
from ..field_components.grid_encodings import Vertices
from ..fields.base import MarchableField
from ..model_components.compiled_march import RENDER_CHUNK as COMPILED_RENDER_CHUNK
from ..model_components.glass import GlassPaths, GlassSurfaces
from ..model_components.compiled_march import (VolumeDensity, compiled_lit_samples, compiled_march_library,
                                               ray_box_stretch, render_marched_compiled)
from ..model_components.marcher import (DRAFT_STOP, EXACT_STOP, OPAQUE_TRANSMITTANCE, render_marched,
                                         render_marched_stopping_early)
from ..model_components.occupancy import OccupancyGrid
from ..model_components.render_output import RenderOutput
from .base import Model, ModelSettings, ParameterGroup


@dataclass(frozen=True)
class MarchConfig:
    step_ratio: float = 0.5  # march step as a fraction of an occupancy cell
    occupancy_warmup: int = 16  # steps before empty space is skipped at all
    occupancy_every: int = 16
    occupancy_alpha_threshold: float = 1e-4  # cells that cannot reach this alpha in one step are empty
    render_alpha_threshold: float = 1e-2  # the same, for rendering only (TrainConfig's)
    fit_box_at: int = 0  # scheduled step at which the box is fitted to the occupied cells; 0: never
    refraction: bool = False  # rays bent through the scene's clear glass (model_components/glass.py)

    @classmethod
    def from_settings(cls, settings: ModelSettings) -> "MarchConfig":
        return cls(settings.grid_step_ratio, settings.occupancy_warmup, settings.occupancy_every,
                   settings.occupancy_alpha_threshold, settings.render_alpha_threshold, settings.fit_box_at,
                   bool(getattr(settings, "refraction", False)))


# Fitting the box: the bounds of the pieces of occupied cells of at least FIT_MIN_PART of the
# largest (floaters are small pieces apart from the scene), widened by FIT_MARGIN_CELLS cells
# (what the occupancy grid marks at the first growth is coarse); done only where that keeps at
# most FIT_MAX_KEPT of the volume (a fitted box: REFIT_MAX_KEPT of it).
FIT_MIN_PART = 0.01
# The occupancy grid's refresh reads the density at every vertex: 10-16 ns a cell on 2 CPU cores
# (262 ms at 255³ cells), a fifth of a 75 ms step when done every 16 steps. Refreshed at most
# once in every cells / OCCUPANCY_CELLS_A_STEP steps, it stays near 5 % of a step on a large
# grid (every 67 steps at 255³) and every occupancy_every steps up to 2 M cells.
OCCUPANCY_CELLS_A_STEP = 250_000
FIT_MARGIN_CELLS = 2
FIT_MAX_KEPT = 0.75
# A fitted box is fitted again after each later growth, where that keeps at most this share of
# it: the finer grid's occupancy bounds the scene closer (and an older field has fewer floaters).
REFIT_MAX_KEPT = 0.9
# Cells a side of the blocks content_corners gives: lego's 10-minute model at 800×800, blocks of
# 8 left 43-50 % of its views' pixels to render, blocks of 16 48-57 % (it covers 30-36 %).
CONTENT_BLOCK = 8
# Pieces of glass a path is traced through (each a body the ray enters and leaves); past them the
# rays beyond are marched straight. Thin-walled glass, where a path meets a second piece most
# (a dish's floor seen through its wall), goes straight (``occupancy_prior.GLASS_MIN_WALL_SHARE``);
# measured at 100×100 after 120 s on 2 CPU cores, 2 pieces gave glass_over_checker 33.06 dB
# against 33.05 with 1, in 4 794 steps against 6 311; a glass cup on a checkerboard, bent, 28.47
# against 28.81 (docs/benchmarks.md, "Rays bent through glass").
GLASS_BODIES = 1


class _GlassLevel(NamedTuple):
    """One level of the rays ``MarchedModel`` marches through glass: the camera's rays, then
    those beyond each piece of glass; ``paths``: where they meet the next piece (None: the last)."""

    origins: Tensor
    directions: Tensor
    t_near: Tensor
    t_far: Tensor
    background: Tensor
    paths: GlassPaths | None


class MarchedModel(Model):
    """A field marched with an occupancy grid; ``prior``: where the scene can be at all."""

    OPAQUE_TRANSMITTANCE = OPAQUE_TRANSMITTANCE
    # Rays per inference pass through PyTorch's march. Measured on 2 CPU cores with the span
    # march (its first version), auto on A.blend's 800×800 views without the occupancy prior:
    # 8192 rays a chunk 3.7 s a view, 32768 4.1 s, 131072 4.8 s (larger blocks leave the caches).
    TORCH_RENDER_CHUNK = 8192
    uses_occupancy_prior = True
    ray_stop = EXACT_STOP  # inference's (march_step_scaled's drafts stop theirs sooner)

    def __init__(self, field: MarchableField, march: MarchConfig, prior: OccupancyPrior | None = None) -> None:
        super().__init__()
        self.field = field
        self.march = march
        self.prior = prior
        self.glass = GlassSurfaces() if march.refraction else None
        self.environment = Environment() if march.refraction else None  # the world seen through the glass
        if self.glass is not None and prior is not None and (surfaces := prior.glass_surfaces()) is not None:
            self.glass.set(*surfaces)
            self.prior = prior.without_glass()  # the field holds nothing at the glass
            if prior.world_light is not None:
                self.environment.start_at(prior.world_light)
        self._fit_tried = False
        self.box_fitted = False  # the field narrowed to a box inside the one it was built over
        self._note: str | None = None
        self._fit_sampling_to_field()
        if prior is not None and getattr(field, "region_aware", False):  # what Blender says the surface is
            field.surface_facts.set(*prior.surface_grid())

    @classmethod
    def of(cls, field_class: type[MarchableField]) -> type["MarchedModel"]:
        """The marched model of ``field_class`` (``GridField`` gives ``GridModel``), made as
        ``Model(settings, box, prior)``: the field from its settings group, over the box."""

        def __init__(self, settings: ModelSettings, box: SceneBounds, prior: OccupancyPrior | None = None) -> None:
            config = getattr(settings, field_class.SETTINGS_GROUP)
            field = field_class(config, box, prior) if field_class.STARTS_FROM_PRIOR else field_class(config, box)
            MarchedModel.__init__(self, field, MarchConfig.from_settings(settings), prior)

        attributes = {"__init__": __init__, "SETTINGS": {field_class.SETTINGS_GROUP: field_class.Config},
                      "__doc__": f"{field_class.__name__} marched with an occupancy grid.", "__module__": cls.__module__}
        if field_class.render_chunk is not None:
            attributes["render_chunk"] = field_class.render_chunk
        return type(field_class.__name__.removesuffix("Field") + "Model", (cls,), attributes)

    @classmethod
    def build(cls, settings: ModelSettings, box: SceneBounds | None, prior: OccupancyPrior | None) -> "MarchedModel":
        """A model made by ``of``, over the scene's box."""
        if box is None:
            raise ValueError(f"the {settings.model} model needs the scene's box")
        return cls(settings, box, prior)  # type: ignore[call-arg]

    def resize(self, vertices: Vertices) -> None:
        """Give a grid field other vertices, and fit the march to its new cells."""
        self.field.resize(vertices)
        self._fit_sampling_to_field()

    def _fit_sampling_to_field(self) -> None:
        """Step length, samples per ray and occupancy cells follow the field's cells; the
        prior, where the dataset has one, marks empty space from the start."""
        cells = self.field.occupancy_cells()
        box_size = (self.field.box_max - self.field.box_min).cpu()
        spacing = min(float(side) / count for side, count in zip(box_size, cells))
        self.step = self.march.step_ratio * spacing
        self.field.march_step = self.step
        self.samples_per_ray = math.ceil(float(box_size.norm()) / self.step) + 1
        # Alpha below this over one step is treated as empty space (in rendering, the second).
        self.density_threshold = -math.log1p(-self.march.occupancy_alpha_threshold) / self.step
        self.render_density_threshold = -math.log1p(-self.march.render_alpha_threshold) / self.step
        device = self.field.box_min.device
        self.occupancy = OccupancyGrid(self.field.box_min, self.field.box_max, cells).to(device)
        self.allowed: Tensor | None = None
        if self.prior is not None:
            box_min, box_max = self.field.box_min.tolist(), self.field.box_max.tolist()
            self.allowed = self.prior.allowed_cells(box_min, box_max, cells).to(device)
            self.occupancy.occupied.copy_(self.allowed)

    @torch.no_grad()
    def update_occupancy(self) -> None:
        """Re-mark empty space from the field's own density, never outside the prior. The
        threshold never exceeds the mean density (Instant-NGP's rule), so a young, still-faint
        field is never pruned to nothing."""
        self.occupancy.mark(self.field.occupied_cells(self.density_threshold, self.allowed, rendering=False))

    @torch.no_grad()
    def render_occupancy(self) -> OccupancyGrid:
        """The grid rendering marches: the training grid's cells less those whose density
        cannot reach ``render_alpha_threshold`` in one step (the threshold never above the
        cells' mean, so a young, faint field keeps its denser part; nerfacc's rule). A trained
        field leaves faint haze over space no view needs: measured at 800×800 on A.blend
        without a prior, skipping it took a view's fine steps from 21.5 M to 4.5 M and
        changed its PSNR by under 0.01 dB. Rebuilt only when the field, the grid or the threshold
        changes."""
        def build() -> OccupancyGrid:
            occupied = self.field.occupied_cells(self.render_density_threshold, self.occupancy.occupied, rendering=True)
            if occupied is None:
                return self.occupancy
            grid = OccupancyGrid(self.field.box_min, self.field.box_max, self.occupancy.cells).to(occupied.device)
            grid.mark(occupied)
            return grid
        return kept_derived(self, "render occupancy", [*self.field.parameters(), self.occupancy.occupied], build,
                            extra=self.render_density_threshold)

    def content_corners(self) -> Tensor:
        """The rendering grid's occupied blocks of ``CONTENT_BLOCK`` cells a side: the march
        reads density only in occupied cells."""
        return self.render_occupancy().occupied_block_corners(CONTENT_BLOCK)

    @contextmanager
    def march_step_scaled(self, scale: float) -> Iterator[None]:
        """The march's step ``scale`` times the trained one inside the block (the samples a ray
        fewer in proportion), and a coarser step's rays stopped as drafts (``DRAFT_STOP``); the
        skip grid stays the one for the trained step, so no cell it marches is dropped. Measured
        on lego at 800×800 (the 10-minute model): twice the step rendered in 0.63 of the time,
        at 31.3 dB against the exact frame (the NeRF's pixels); 31.2 dB with the draft's stop."""
        saved = self.step, self.samples_per_ray, self.ray_stop
        if scale != 1.0:
            self.step = self.field.march_step = saved[0] * scale
            self.samples_per_ray = math.ceil((saved[1] - 1) / scale) + 1
            self.ray_stop = DRAFT_STOP if scale > 1.0 else EXACT_STOP
        try:
            yield
        finally:
            self.step, self.samples_per_ray, self.ray_stop = saved
            self.field.march_step = saved[0]

    def density_at(self, points: Tensor) -> Tensor:
        return self.field.density(points)

    def surface_function(self) -> Callable[[Tensor], Tensor] | None:
        return self.field.surface_function()

    def regularisation(self, generator: torch.Generator | None = None) -> Tensor | None:
        return self.field.regularisation(generator)

    def colour_at(self, points: Tensor, directions: Tensor) -> Tensor:
        return self.field.colour(points, directions)

    def parameter_groups(self) -> list[ParameterGroup]:
        encoding = self.field.encoding_parameters()
        ids = {id(p) for p in encoding}
        networks = [p for p in self.parameters() if id(p) not in ids]
        if not encoding:  # a field of networks only trains them at the model's main rate
            return [ParameterGroup("networks", networks, "learning_rate")]
        return [ParameterGroup("encoding", encoding, "learning_rate"),
                ParameterGroup("networks", networks, "network_learning_rate")]

    def before_step(self, iteration: int, scheduled: int, steps_left: float | None = None) -> bool:
        """Fitting the box at ``fit_box_at`` (tried again at the step after each later growth:
        a young field's floaters can span the box at the first, and a finer grid bounds the
        scene closer), the field's schedule (a grid's upsampling), then the occupancy grid's refresh
        (every ``occupancy_every`` steps taken, or fewer on a large grid:
        ``occupancy_refresh_every``)."""
        fit_at = self.march.fit_box_at
        fitted = (fit_at > 0 and scheduled >= fit_at and iteration >= self.march.occupancy_warmup
                  and not self._fit_tried and self.fit_box())
        grown = self.field.before_step(scheduled, steps_left)
        if grown:
            self._fit_sampling_to_field()
            self.update_occupancy()
            self._fit_tried = False  # the box is fitted (again) at the next step, from the grown grid's occupancy
        if iteration >= self.march.occupancy_warmup and iteration % self.occupancy_refresh_every() == 0:
            self.update_occupancy()
        return fitted or grown

    def occupancy_refresh_every(self) -> int:
        """Steps between the occupancy grid's refreshes: ``occupancy_every``, or on a grid of
        more than that many times ``OCCUPANCY_CELLS_A_STEP`` cells, its cells over that."""
        return max(self.march.occupancy_every, math.ceil(math.prod(self.occupancy.cells) / OCCUPANCY_CELLS_A_STEP))

    def fit_box(self) -> bool:
        """Narrow the field to the box around its occupied cells (TensoRF's shrinking): its
        cells then shrink with the box, so the same parameters hold finer detail where the
        scene is. Tried at ``fit_box_at`` and after each later growth (a fitted box again where
        that keeps at most ``REFIT_MAX_KEPT`` of it); True when the field changed."""
        self._fit_tried = True
        # The cells rendering keeps (able to reach render_alpha_threshold in a step): the
        # training grid's also keep the faint haze a young field has everywhere.
        bounds = self.render_occupancy().occupied_bounds(FIT_MARGIN_CELLS, FIT_MIN_PART)
        if bounds is None:
            return False
        kept = math.prod(hi - lo for lo, hi in zip(bounds.box_min, bounds.box_max)) / math.prod(self.field.extent)
        limit = REFIT_MAX_KEPT if self.box_fitted else FIT_MAX_KEPT
        if kept > limit:
            if not self.box_fitted:
                self._note = (f"box kept: what the field has filled spans {kept:.0%} of its volume "
                              f"(it is narrowed where that is at most {FIT_MAX_KEPT:.0%})")
            return False
        built = math.prod(self.field.built_extent)
        if not self.field.fit_box(bounds):
            return False
        again = " again" if self.box_fitted else ""
        self.box_fitted = True
        self._fit_sampling_to_field()
        self.update_occupancy()
        sides = " × ".join(f"{hi - lo:.2f}" for lo, hi in zip(bounds.box_min, bounds.box_max))
        self._note = (f"box fitted{again} to the occupied cells: {sides} ({math.prod(self.field.extent) / built:.0%} "
                      f"of the built box), grids {' × '.join(map(str, self.field.vertices))} vertices")
        return True

    def coarse_detail(self) -> float | None:
        return self.field.coarse_detail()

    def after_step(self) -> None:
        self.field.after_step()

    def take_note(self) -> str | None:
        notes = [note for note in (self._note, self.field.take_note()) if note]
        self._note = None
        return "; ".join(notes) or None

    def match_state(self, state: dict[str, Tensor]) -> None:
        if self.glass is not None:
            self.glass.match_state(state, "glass.")
        field_state = {key.removeprefix("field."): value for key, value in state.items() if key.startswith("field.")}
        if self.field.match_state(field_state):
            self._fit_sampling_to_field()
        self.box_fitted = self.field.extent != self.field.built_extent
        self._fit_tried = self._fit_tried or self.box_fitted

    def _density_volume(self) -> Tensor | None:
        """The field's density volume (None if it has none), rebuilt only when the field
        has changed."""
        return kept_derived(self, "density volume", self.field.parameters(), self.field.density_volume)

    @property
    def render_chunk(self) -> int:
        """Rays per inference pass: the compiled march's ``RENDER_CHUNK`` where it renders,
        else ``TORCH_RENDER_CHUNK``."""
        compiled = self._compiled_density(next(self.parameters()).device)
        return COMPILED_RENDER_CHUNK if compiled is not None else self.TORCH_RENDER_CHUNK

    def _compiled_density(self, device: torch.device) -> tuple[VolumeDensity, object] | None:
        """The density volume and the compiled march's library where inference can use them:
        on the CPU, for a field whose density is an activated trilinear read, with a C
        compiler present. Else None: the PyTorch march renders the same image."""
        activation = self.field.volume_activation() if device.type == "cpu" else None
        if activation is None:
            return None
        library, _ = compiled_march_library()
        volume = self._density_volume() if library is not None else None
        if volume is None:
            return None
        return VolumeDensity(volume[0, 0], *activation), library

    def _frozen_density(self, x: Tensor, directions: Tensor) -> Tensor:
        """Density without gradients: through the field's density volume where it has one,
        except in training, whose weights change every step: there the volume would be
        rebuilt each step (bench-step measured 15 ms of a 52 ms step at 256³) for a few
        thousand samples."""
        if self.training:
            return self.field.density_along(x, directions)
        return self.field.density_from_volume(self._density_volume(), x, directions)

    def _within_field_box(self, origins: Tensor, directions: Tensor, t_near: Tensor,
                          t_far: Tensor) -> tuple[Tensor, Tensor]:
        """``[t_near, t_far]`` narrowed to each ray's stretch inside the field's box (empty,
        ``t_far == t_near``, for a ray that misses it)."""
        return ray_box_stretch(origins, directions, self.field.box_min, self.field.box_max, within=(t_near, t_far))

    def _render_compiled_inside(self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
                                density: VolumeDensity, library, march: dict) -> RenderOutput:
        """The compiled march of the rays that pass through the field's box; the others are the
        background, with no per-ray work (the colour's share of a ray, the march's set-up): a
        fitted box leaves about a third of lego's 800×800 views outside it."""
        count = origins.shape[0]
        inside = (t_far > t_near).nonzero().squeeze(1)
        every = inside.numel() == count
        rays = (origins, directions, t_near, t_far) if every else [
            t.index_select(0, inside) for t in (origins, directions, t_near, t_far)]
        background = torch.as_tensor(march["background"], dtype=origins.dtype, device=origins.device)
        if not every and background.dim() == 2:  # a colour a ray (training's random backgrounds)
            march = {**march, "background": background.index_select(0, inside)}
        out = render_marched_compiled(*rays, density=density, ray_colour=self._ray_colour(rays[1]), library=library,
                                      **march)
        if every:
            return out
        rgb = background.to(out.rgb.dtype).expand(count, 3).clone()
        rgb[inside] = out.rgb
        depth, opacity = out.depth.new_zeros(count), out.opacity.new_zeros(count)
        depth[inside], opacity[inside] = out.depth, out.opacity
        return RenderOutput(rgb=rgb, depth=depth, opacity=opacity, weights=None, t_edges=None)

    def _ray_colour(self, directions: Tensor):
        """What inference's march gives each packed sample of rays along ``directions``: its
        colour, or its appearance features where the field defers colour (``shade_fn``)."""
        if self.field.shade_fn() is not None:
            return self.field.ray_features(directions)
        return self.field.ray_colour(directions, colour_network_dtype(directions.device))

    def forward(
        self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
        background: Tensor | float = 1.0, generator: torch.Generator | None = None,
    ) -> list[RenderOutput]:
        paths = self.glass.trace(origins, directions) if self.glass is not None else None
        if paths is None:
            return self._march_rays(origins, directions, t_near, t_far, background, generator)
        return [self._through_glass(origins, directions, t_near, t_far, background, paths, generator)]

    def _through_glass(self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
                       background: Tensor | float, paths: GlassPaths, generator: torch.Generator | None
                       ) -> RenderOutput:
        """Rays of which ``paths`` meet glass: each is marched up to the glass over no
        background, and the rays beyond it (the one leaving the glass and the one its surface
        reflects) along their own segments, traced again where they meet glass again (a dish's
        floor seen through its wall, a glass's far side), up to ``GLASS_BODIES`` pieces of glass
        a path; the last ones over the world's light (``Environment``). Every segment of every
        level is marched in one pass; what shows at each glass is then laid under its ray's
        samples, the deepest level first."""
        box_min, box_max = self.field.box_min.to(origins.dtype), self.field.box_max.to(origins.dtype)
        count = origins.shape[0]
        levels: list[_GlassLevel] = []
        backgrounds = torch.as_tensor(background, dtype=origins.dtype, device=origins.device).expand(count, 3)
        while True:
            if paths is not None:  # marched up to the glass, over nothing: what is beyond shows there
                met = paths.rays
                near_met = t_near.index_select(0, met)
                t_far = t_far.index_put((met,), torch.maximum(torch.minimum(t_far.index_select(0, met),
                                                                            paths.t_entry.to(t_far.dtype)), near_met))
                backgrounds = backgrounds.index_fill(0, met, 0.0)
            levels.append(_GlassLevel(origins, directions, t_near, t_far, backgrounds, paths))
            if paths is None:
                break
            origins, directions = paths.origins, paths.directions
            _, t_far, _ = ray_box_intersection(origins, directions, box_min, box_max)
            t_near = torch.zeros_like(t_far)
            backgrounds = self.environment(directions).to(origins.dtype)
            paths = self.glass.trace(origins, directions) if len(levels) < GLASS_BODIES else None
        out = self._march_rays(*(torch.cat([getattr(level, name) for level in levels])
                                 for name in ("origins", "directions", "t_near", "t_far", "background")), generator)[0]
        rgb, opacity = (values.split([level.origins.shape[0] for level in levels]) for values in (out.rgb, out.opacity))
        seen_beyond = rgb[-1]
        for index in range(len(levels) - 2, -1, -1):
            paths = levels[index].paths
            seen = paths.colour_seen(seen_beyond).to(out.rgb.dtype)
            through = (1.0 - opacity[index].index_select(0, paths.rays))[:, None]
            seen_beyond = rgb[index].index_add(0, paths.rays, through * seen)
        return RenderOutput(rgb=seen_beyond, depth=out.depth[:count], opacity=out.opacity[:count],
                            weights=None if out.weights is None else out.weights[:count],
                            t_edges=None if out.t_edges is None else out.t_edges[:count],
                            field_samples=out.field_samples)

    def _march_rays(self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
                    background: Tensor | float, generator: torch.Generator | None) -> list[RenderOutput]:
        if self.box_fitted:  # the rays' bounds are the scene's; the field now holds less
            t_near, t_far = self._within_field_box(origins, directions, t_near, t_far)
        march = dict(occupancy=self.occupancy, step=self.step, steps=self.samples_per_ray, background=background,
                     density_fn=self._frozen_density, shade_fn=self.field.shade_fn())
        if not self.training and not torch.is_grad_enabled():
            march["occupancy"], march["stop"] = self.render_occupancy(), self.ray_stop
            compiled = self._compiled_density(origins.device)
            if compiled is not None:
                density, library = compiled
                del march["density_fn"]
                return [self._render_compiled_inside(origins, directions, t_near, t_far, density, library, march)]
            return [render_marched_stopping_early(origins, directions, t_near, t_far,
                                                  ray_colour=self._ray_colour(directions), **march)]
        offset, lit_fn, lit_pass_fn = None, None, None
        if self.training:  # one random offset per ray: unbiased, and every step still covered
            offset = torch.rand((origins.shape[0], 1), generator=generator, device=origins.device,
                                dtype=origins.dtype)
            density = self.field.compiled_density() if origins.device.type == "cpu" else None
            if density is not None:  # the march and its density pass in one compiled pass a ray
                lit_pass_fn = self.field.compiled_lit_pass()  # and the field's pass and compositing in one more
                lit_fn = compiled_lit_samples(self.occupancy, self.step, self.samples_per_ray, density,
                                              record=lit_pass_fn is not None)
        return [render_marched(origins, directions, t_near, t_far, field_fn=self.field, offset=offset,
                               lit_fn=lit_fn, lit_pass_fn=lit_pass_fn, **march)]
