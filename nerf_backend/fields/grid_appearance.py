"""Colour from a factorised feature grid through a small MLP (TensoRF's appearance), for any
field whose config names ``appearance_channels``, ``appearance_dims``, ``hidden_width``,
``view_dependent`` and ``direction_frequencies``: the grid field's colour and the surface
field's are this one."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerf_contract.dataset_layout import APPEARANCE_REGIONS

from ..core.field_functions import RayColourFn, ShadeFn
from ..field_components.compiled_colour import (compiled_ray_colour, compiled_ray_features, compiled_shade,
                                                compiled_shade_training)
from ..field_components.encodings import PositionalEncoding
from ..field_components.grid_encodings import VectorMatrixGrid, Vertices
from ..field_components.surface_facts import SurfaceFacts
from .base import SampleCost, mlp_flops

# The regions the colour treats apart, by their index in the prior's ``regions`` array.
_DIFFUSE, _METAL = APPEARANCE_REGIONS.index("diffuse"), APPEARANCE_REGIONS.index("metal")
# A thin film's colour is the view reflected (what the coat mirrors) tinted by interference
# that follows the angle between the view and the normal: it sees both the view and its reflection.
_THIN_FILM = APPEARANCE_REGIONS.index("thin_film")


class GridAppearance:
    """Mixed into a ``MarchableField``: ``build_appearance`` in its ``__init__``, then
    ``colour(x, d)``. The viewing direction's encoding is an input only when the config is
    view-dependent.

    With ``deferred_colour`` in the config (SNeRG's deferred shading), the marched samples carry
    the appearance grid's features, not colours (``sample_appearance``); the march composites
    them along each ray and ``shade_fn`` runs the basis and the network once a ray on their
    weighted mean. The basis is linear, so compositing the grid's features before it is the
    same as after. A single point's ``colour`` is the network on its own features, as before.

    With ``region_appearance`` in the config, the network's direction inputs follow what the
    scene's surface is made of (``direction_inputs``, from ``surface_facts``: the dataset's
    prior and true surface, set by the model); with deferred colour each sample carries what
    they are made of beside its features (``direction_parts``), composited alike."""

    def build_appearance(self, config, vertices: Vertices, extra_inputs: int = 0) -> None:
        """The appearance grid and MLP; ``extra_inputs``: features of the field's own that
        ``colour`` is given besides (the surface field's normal)."""
        self.appearance_grid = VectorMatrixGrid(config.appearance_channels, vertices)
        self.appearance_basis = nn.Linear(self.appearance_grid.out_dims, config.appearance_dims, bias=False)
        self.direction_encoding = PositionalEncoding(3, config.direction_frequencies)
        colour_in = config.appearance_dims + (self.direction_encoding.out_dims if config.view_dependent else 0)
        if self.region_aware:
            self.reflection_encoding = PositionalEncoding(3, config.reflection_frequencies)
            self.surface_facts = SurfaceFacts()
            colour_in += self.reflection_encoding.out_dims
        colour_in += extra_inputs
        self.colour_mlp = nn.Sequential(
            nn.Linear(colour_in, config.hidden_width), nn.ReLU(inplace=True),
            nn.Linear(config.hidden_width, config.hidden_width), nn.ReLU(inplace=True),
            nn.Linear(config.hidden_width, 3),
        )

    def colour(self, x: Tensor, directions: Tensor) -> Tensor:
        return self.colour_with(x, directions)

    @property
    def region_aware(self) -> bool:
        """Whether the colour's direction inputs follow the scene's appearance regions."""
        return bool(getattr(self.config, "region_appearance", False)) and bool(self.config.view_dependent)

    def direction_inputs(self, directions: Tensor, x: Tensor | None = None) -> Tensor | None:
        """The colour network's direction inputs for samples at ``x`` seen along ``directions``:
        the view's encoding where the field is view-dependent (None where not); region-aware,
        that encoding where the region is neither diffuse nor metal, beside the encoding of the
        view reflected about the true surface's normal where it is metal or thin film and a normal
        is known (Ref-NeRF's reflected direction, here from Blender's mesh; a thin film keeps the
        view too), and nothing of the view where it is diffuse (``direction_parts``, then
        ``encode_directions``). On thin_film_coat (100×100, 120 s, region appearance forced) the
        film seeing its reflection beside the view scored 37.77 dB, the view alone 37.62. Glossy dielectrics keep
        the view: on A.blend (roughness 0.4) the reflected view scored 0.97 dB less at 100×100
        after 120 s (docs/benchmarks.md, "Colour shaped by the scene's materials")."""
        if not self.config.view_dependent:
            return None
        if not self.region_aware:
            return self.direction_encoding(directions)
        if x is None:
            raise ValueError("region-aware colour needs the samples' points")
        return self.encode_directions(directions, self.direction_parts(directions, x))

    def direction_parts(self, directions: Tensor, x: Tensor) -> Tensor:
        """``[P, 5]`` per sample: whether the view itself is an input (1, or 0 on diffuse and
        metal surfaces), the reflected view times whether it is an input (3: on metal and thin
        film), and whether it is (1). Deferred colour composites these five along a ray, not their encodings (42
        values): a ray's reflected views near one surface differ little, so the encoding of
        their mean stands for the mean of their encodings."""
        region = self.surface_facts.region_at(x)
        parts = directions.new_zeros((x.shape[0], 5))
        parts[:, 0] = ((region != _DIFFUSE) & (region != _METAL)).to(parts.dtype)
        reflecting = ((region == _METAL) | (region == _THIN_FILM)).nonzero().squeeze(1)  # normals read only there
        if reflecting.numel():
            at = x.index_select(0, reflecting)
            normal, seen = self.surface_facts.normal_at(at), directions.index_select(0, reflecting)
            known = normal.abs().sum(dim=1) > 0  # no surface near: the view as before
            reflected = seen - 2.0 * (seen * normal).sum(dim=1, keepdim=True) * normal
            view = (~known) | (region.index_select(0, reflecting) == _THIN_FILM)
            parts[reflecting] = torch.cat([view[:, None].to(parts.dtype), reflected * known[:, None],
                                           known[:, None].to(parts.dtype)], dim=1)
        return parts

    def encode_directions(self, directions: Tensor, parts: Tensor) -> Tensor:
        """The direction inputs from ``direction_parts`` (or their weighted mean along rays):
        the view's encoding times its share, and the encoding of the (mean) reflected view's
        direction times its share."""
        reflected = parts[:, 1:4]
        length = reflected.norm(dim=1, keepdim=True)
        unit = torch.where(length > 1e-6, reflected / length.clamp(min=1e-6), torch.zeros_like(reflected))
        return torch.cat([self.direction_encoding(directions) * parts[:, :1],
                          self.reflection_encoding(unit) * parts[:, 4:5]], dim=1)

    def match_surface_facts(self, state: dict[str, Tensor]) -> None:
        """Take the surface facts' shapes from a checkpoint (``match_state``)."""
        if self.region_aware:
            self.surface_facts.match_state(state, "surface_facts.")

    @property
    def deferred(self) -> bool:
        """Whether marched samples carry appearance features, shaded once a ray (``shade_fn``)."""
        return bool(getattr(self.config, "deferred_colour", False))

    def shade_fn(self) -> ShadeFn | None:
        """``MarchableField.shade_fn``: the colour of a ray's mean appearance features (and
        region-aware, of its mean direction inputs beside them)."""
        if not self.deferred:
            return None
        if self.region_aware:
            width = self.appearance_grid.out_dims
            return lambda mean, directions: self.colour_from_grid(mean[:, :width],
                                                                  self.encode_directions(directions, mean[:, width:]))
        # On the CPU, the compiled passes: inference's, or training's.
        compiled = compiled_shade(self) if not torch.is_grad_enabled() else compiled_shade_training(self)
        if compiled is not None:
            return compiled
        return lambda mean, directions: self.colour_from_grid(mean, self.direction_inputs(directions))

    def sample_appearance(self, grid_features: Tensor, directions: Tensor, x: Tensor) -> Tensor:
        """What a marched sample at ``x`` carries: its colour, or with deferred colour its
        features (region-aware, with its direction inputs beside them)."""
        if not self.deferred:
            return self.colour_from_grid(grid_features, self.direction_inputs(directions, x))
        if self.region_aware:
            return torch.cat([grid_features.float(), self.direction_parts(directions, x)], dim=1)
        return grid_features

    def ray_features(self, directions: Tensor) -> RayColourFn:
        """``MarchableField.ray_features``: the appearance grid's features of packed samples
        (on the CPU, with the compiled pass that composites them: ``compiled_ray_features``)."""
        if self.region_aware:
            return lambda x, ray: self.sample_appearance(self.appearance_grid(self.normalise(x)).float(),
                                                         directions.index_select(0, ray), x)
        compiled = compiled_ray_features(self) if directions.device.type == "cpu" else None
        if compiled is not None:
            return compiled
        return lambda x, ray: self.appearance_grid(self.normalise(x)).float()

    def colour_with(self, x: Tensor, directions: Tensor, extra: Tensor | None = None) -> Tensor:
        """``colour``, with the ``extra_inputs`` features given (``[P, extra_inputs]``)."""
        return self.colour_from_grid(self.appearance_grid(self.normalise(x)), self.direction_inputs(directions, x),
                                     extra)

    def colour_from_grid(self, grid_features: Tensor, direction_inputs: Tensor | None,
                         extra: Tensor | None = None) -> Tensor:
        """``colour_with`` from the appearance grid's features at the points, already read, and
        their ``direction_inputs``."""
        features = [self.appearance_basis(grid_features)]
        if direction_inputs is not None:
            features.append(direction_inputs.to(features[0].dtype))
        if extra is not None:
            features.append(extra.to(features[0].dtype))
        return torch.sigmoid(self.colour_mlp(torch.cat(features, dim=-1) if len(features) > 1 else features[0]).float())

    def ray_colour(self, directions: Tensor, dtype: torch.dtype = torch.float32) -> RayColourFn:
        """``MarchableField.ray_colour``, for inference (no gradients): the viewing direction's
        share of the colour MLP's first layer (its encoding times those columns, plus the bias)
        is the same for every sample of a ray, so it is computed once a ray and each sample adds
        its ray's row (measured on a glass view at 800×800, 2.5 M samples of 640 000 rays:
        colour 0.61 → 0.49 s); the appearance basis is folded into the first layer (one product
        of the grid's features instead of two); and the products run in ``dtype``. The same
        sums as ``colour``, in another order (and rounded to ``dtype``)."""
        first = self.colour_mlp[0]
        appearance = self.config.appearance_dims
        if not self.config.view_dependent or first.in_features != appearance + self.direction_encoding.out_dims:
            return super().ray_colour(directions, dtype)  # no direction, region-aware, or features of the field's own
        compiled = compiled_ray_colour(self, directions, dtype)
        if compiled is not None:  # the CPU's compiled pass (field_components/compiled_colour.py)
            return compiled
        with torch.no_grad():
            per_ray, grid_weight = (t.to(dtype) for t in self.first_layer_parts(directions))
            layers = [(layer.weight.t().to(dtype), layer.bias.to(dtype))
                      for layer in self.colour_mlp[1:] if isinstance(layer, nn.Linear)]

        @torch.no_grad()
        def colour(x: Tensor, ray: Tensor) -> Tensor:
            hidden = torch.addmm(per_ray.index_select(0, ray), self.appearance_grid(self.normalise(x)).to(dtype),
                                 grid_weight)
            for weight, bias in layers:
                hidden = torch.addmm(bias, hidden.relu_(), weight)
            return torch.sigmoid(hidden.float())

        return colour

    @torch.no_grad()
    def first_layer_parts(self, directions: Tensor) -> tuple[Tensor, Tensor]:
        """The colour MLP's first layer split for ``ray_colour`` (float32): each ray's share
        ``[R, H]`` (its direction's encoding times those columns, plus the bias) and the grid
        features' weights ``[3·C, H]`` with the appearance basis folded in."""
        first = self.colour_mlp[0]
        per_ray = F.linear(self.direction_encoding(directions.float()), first.weight[:, self.config.appearance_dims:],
                           first.bias)
        return per_ray, self.folded_grid_weight()

    @torch.no_grad()
    def folded_grid_weight(self) -> Tensor:
        """The first layer's weights for the grid's features ``[3·C, H]``, the appearance basis
        folded in (one product of the features instead of two)."""
        first = self.colour_mlp[0]
        return (first.weight[:, :self.config.appearance_dims] @ self.appearance_basis.weight).t()

    def shade_cost(self) -> SampleCost | None:
        """Deferred colour's network once a shaded ray (None without deferred colour): the
        basis and the network as PyTorch runs them, or with the basis folded into the first
        layer (the compiled shading), whichever is fewer FLOPs; a ray's direction encoded."""
        if not self.deferred:
            return None
        network = mlp_flops(self.colour_mlp)
        first = self.colour_mlp[0]
        unfolded = mlp_flops(self.appearance_basis) + network
        folded = network + 2 * (self.appearance_grid.out_dims - self.config.appearance_dims) * first.out_features
        return SampleCost(0, min(unfolded, folded))

    def appearance_cost(self) -> SampleCost:
        """One colour sample: each channel of a component reads 4 plane and 2 line values, and
        interpolating takes a multiply-add of each; then the basis and the network, or with
        deferred colour a multiply-add a feature into its ray's sum (the network runs once a ray)."""
        gathers = 3 * (4 + 2) * self.config.appearance_channels
        if self.deferred:
            return SampleCost(gathers, 2 * gathers + 2 * self.appearance_grid.out_dims)
        return SampleCost(gathers, 2 * gathers + mlp_flops(self.appearance_basis) + mlp_flops(self.colour_mlp))
