"""One decision a rule makes about a run's settings, and how the user's ``--set`` overrides it.

Every rule that shapes a preset to the scene (``auto``, the surface preset's softness and
opacity) records what it chose and why in the run's ``config.json``. A setting the user gave
with ``--set`` is theirs: the rule keeps it and records what it would have chosen instead.

Example:
    >>> from nerf_backend.configs.presets import PRESETS
    >>> value, record = decide("surface.opacity", "neus", "a band bounds the surface",
    ...                        PRESETS["surface"], frozenset({"surface.opacity"}))
    >>> value, record["reason"]
    ('volsdf', "set with --set surface.opacity; the rule would choose 'neus': a band bounds the surface")
"""

from __future__ import annotations

from ..configs.train_config import TrainConfig


def decide(key: str, chosen, reason: str, config: TrainConfig, user_set: frozenset[str],
           **details) -> tuple[object, dict]:
    """The value of the dotted setting ``key`` (``grid.resolution``): ``config``'s where the
    user set it (``user_set``), else ``chosen``; with the record ``{"value", **details,
    "reason"}`` for the run's decisions."""
    if key in user_set:
        value = _setting(config, key)
        return value, {"value": value, **details,
                       "reason": f"set with --set {key}; the rule would choose {chosen!r}: {reason}"}
    return chosen, {"value": chosen, **details, "reason": reason}


def _setting(config: TrainConfig, key: str):
    """The value of a dotted setting (``grid.resolution``)."""
    value = config
    for part in key.split("."):
        value = getattr(value, part)
    return value
