"""One frozen plan a run trains by, and the one pass that makes it: the preset (or a resumed
run's stored config), the user's ``--set``, then every rule of ``rules.RULES`` in order, each
seeing the facts and the plan so far. ``config.json`` records the whole plan; the trainer runs
it and decides nothing.

A rule proposes (``Proposal``) a value for one setting: a ``TrainConfig`` setting (dotted:
``grid.resolution``) or one of the plan's own (``device``, ``max_seconds``...). A setting
the user gave with ``--set`` is theirs: the plan keeps it and records what the rule would have
chosen instead.

Example:
    >>> from nerf_backend.configs.presets import PRESETS
    >>> plan = RunPlan(config=PRESETS["surface"])
    >>> chosen = plan.decided(Proposal("surface_opacity", "surface.opacity", "neus", "a band bounds the surface"),
    ...                       frozenset({"surface.opacity"}))
    >>> chosen.config.surface.opacity, chosen.decisions["surface_opacity"]["reason"]
    ('volsdf', "set with --set surface.opacity; the rule would choose 'neus': a band bounds the surface")
    >>> plan.decided(Proposal("surface_opacity", "surface.opacity", "neus", "why"), frozenset()).config.surface.opacity
    'neus'
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import torch

from ..configs.train_config import TrainConfig
from ..model_components.ray_bounds import RayBounds
from .facts import RunFacts


@dataclass(frozen=True)
class Proposal:
    """A rule's choice for one setting (``key``; None: a decision recorded only), recorded as
    ``name`` in ``config.json``'s decisions with its reason and details."""

    name: str
    key: str | None
    value: Any
    reason: str
    details: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class RunPlan:
    """What a run trains with, every value decided before its first step."""

    config: TrainConfig
    dataset: Path = Path()
    seed: int = 0
    device: torch.device = torch.device("cpu")
    max_seconds: float | None = None  # total training seconds (None: by iterations)
    schedule_seconds: float | None = None  # the budget the schedule spans (None: by iterations)
    stop_at_iterations: bool = True  # False: a time budget alone ends the run
    train_views: int = 0  # the first this many training views
    image_size: tuple[int, int] = (0, 0)
    ray_bounds: RayBounds = RayBounds()
    prior_kind: str | None = None  # the occupancy prior the model starts from (None: none)
    coarse_image_pixel: float | None = None  # coarse-to-fine images: a full-size pixel's footprint
    decisions: Mapping[str, dict] = field(default_factory=dict)

    def decided(self, proposal: Proposal, user_set: frozenset[str]) -> "RunPlan":
        """This plan with ``proposal`` applied (kept as the user's where they ``--set`` it) and recorded."""
        value, reason, key = proposal.value, proposal.reason, proposal.key
        if key in user_set:
            value = self.config.setting(key)
            reason = f"set with --set {key}; the rule would choose {proposal.value!r}: {reason}"
        config = self.config if key is None or key in _PLAN_FIELDS else self.config.with_setting(key, value)
        decisions = {**self.decisions, proposal.name: {"value": _recorded(value), **proposal.details, "reason": reason}}
        own = {key: value} if key in _PLAN_FIELDS else {}
        return dataclasses.replace(self, config=config, decisions=decisions, **own)

    def record(self) -> dict:
        """The run's config.json: the whole plan."""
        return {
            "dataset": str(self.dataset),
            "preset": self.config.preset,
            "seed": self.seed,
            "device": str(self.device),
            "max_seconds": self.max_seconds,
            "schedule_seconds": self.schedule_seconds,
            "stop_at_iterations": self.stop_at_iterations,
            "config": self.config.to_dict(),
            "decisions": dict(self.decisions),
            "background": "white (RGBA composited as rgb·α + 1 − α)",
            "image_size": list(self.image_size),
            "train_views": self.train_views,
        }


# The plan's own settings a rule may propose (the rest of a proposal's keys are the config's).
_PLAN_FIELDS = frozenset(f.name for f in dataclasses.fields(RunPlan)) - {"config", "decisions"}

Rule = Callable[[RunFacts, RunPlan], Iterable[Proposal]]


def plan_run(facts: RunFacts, rules: Iterable[Rule]) -> RunPlan:
    """The plan that starts from ``facts.start`` (a new run's preset with the user's ``--set``,
    or a resumed run's stored settings and decisions), then each of ``rules`` in order. Reads
    nothing."""
    stored = facts.stored or {}
    plan = RunPlan(config=facts.start, dataset=facts.dataset, seed=stored.get("seed", facts.request.seed),
                   image_size=(facts.train_split.intrinsics.width, facts.train_split.intrinsics.height),
                   decisions=dict(stored.get("decisions", {})))
    return apply_rules(facts, plan, rules)


def apply_rules(facts: RunFacts, plan: RunPlan, rules: Iterable[Rule]) -> RunPlan:
    """``plan`` with each of ``rules`` in order deciding on the facts and the plan so far."""
    user_set = facts.request.user_set
    for rule in rules:
        for proposal in rule(facts, plan):
            plan = plan.decided(proposal, user_set)
    return plan


def _recorded(value):
    """A value as config.json holds it."""
    if isinstance(value, RayBounds):
        return value.describe()
    if isinstance(value, torch.device):
        return str(value)
    return list(value) if isinstance(value, tuple) else value
