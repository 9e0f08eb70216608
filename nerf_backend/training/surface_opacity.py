"""The surface preset's opacity (``surface.opacity``), from whether the dataset's prior bounds
the surface.

NeuS's opacity puts a silhouette exactly at the distance's zero level, where VolSDF's density
puts it outside and so pulls the surface inward (``fields/surface_field.py``). But NeuS never
shows a surface that rays only leave, so nothing in the images removes one: on its own it left
flaps behind A.blend's cube (F-score 0.445 against VolSDF's 0.486 at 800×800). Blender's prior,
where the dataset has one, bounds the distance on both sides of a thin band
(``field_components/surface_band.py``), which leaves no room for such flaps; there NeuS wins on
both counts (A.blend, 600 s at 800×800: F-score 0.980 against 0.957, 33.43 against 30.28 dB;
100×100, 300 s: 0.974 against 0.874). Without that prior VolSDF stays.

Example:
    >>> from nerf_backend.configs.presets import PRESETS
    >>> config, decision = surface_opacity(PRESETS["surface"], None)
    >>> config.surface.opacity, decision["surface_opacity"]["value"]
    ('volsdf', 'volsdf')
"""

from __future__ import annotations

import dataclasses

from ..configs.train_config import TrainConfig
from ..data.occupancy_prior import OccupancyPrior
from .decision import decide


def surface_opacity(config: TrainConfig, prior: OccupancyPrior | None,
                    user_set: frozenset[str] = frozenset()) -> tuple[TrainConfig, dict]:
    """``config`` (a surface preset) with its opacity chosen by ``prior`` (the one the model
    gets), and the decision with its reason (the user's ``--set surface.opacity`` is kept)."""
    surface = config.surface
    bounded = surface.prior_band and prior is not None and prior.bounds_the_surface
    chosen = "neus" if bounded else "volsdf"
    reason = ("Blender's occupancy prior bounds the surface to a band (surface.prior_band), where NeuS's "
              "unbiased silhouettes leave no flaps" if bounded else
              "no prior bounds the surface (none, or surface.prior_band off): NeuS would leave surfaces no ray "
              "shows, VolSDF's density does not")
    value, record = decide("surface.opacity", chosen, reason, config, user_set)
    shaped = config.with_settings(surface=dataclasses.replace(surface, opacity=value))
    return shaped, {"surface_opacity": record}
