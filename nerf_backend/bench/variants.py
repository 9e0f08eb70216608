"""Variants: a preset with changes (``NAME=PRESET+KEY=VALUE+...``), and the NeRF paper's
ablations as variants, with the order its Table 2 implies."""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_PRESETS = "preview,fast,auto,paper"
# The NeRF paper's ablations (its Table 2), as changes to a NeRF preset.
ABLATIONS = {
    "no_pe": ("field.position_frequencies=0", "field.direction_frequencies=0"),
    "no_view_dependence": ("field.view_dependent=false",),
    "no_hierarchical": ("sampling.fine_samples=0",),
    "50_views": ("max_train_views=50",),
    "25_views": ("max_train_views=25",),
    "L5": ("field.position_frequencies=5",),
    "L15": ("field.position_frequencies=15",),
}
# What the paper found (Table 2: 31.01 complete; 28.77 no PE, 27.66 no view dependence,
# 30.06 no hierarchical; 29.79 with 50 views, 27.78 with 25; 30.59 with L = 5, 30.81 with 15):
# (better, worse) pairs that its order implies.
PAPER_ORDER = (
    ("full", "no_pe"), ("full", "no_view_dependence"), ("full", "no_hierarchical"),
    ("full", "50_views"), ("50_views", "25_views"), ("full", "L5"), ("full", "L15"),
)


def ablation_variants(base: str) -> list[str]:
    """Variant specs for the ablations of ``base``: the full model first, named BASE_full."""
    return [f"{base}_full={base}"] + [f"{base}_{name}={'+'.join((base,) + changes)}" for name, changes in ABLATIONS.items()]


def ablation_order(variants: list[dict]) -> list[dict]:
    """Each of the paper's (better, worse) pairs found among ``variants`` (named as
    ``ablation_variants`` names them), with whether this bench's PSNR agrees."""
    by_suffix = {}
    for v in variants:
        for suffix in ("full", *ABLATIONS):
            if v["name"].endswith("_" + suffix):
                by_suffix[suffix] = v
    checks = []
    for better, worse in PAPER_ORDER:
        if better in by_suffix and worse in by_suffix:
            high, low = by_suffix[better]["final"]["psnr"], by_suffix[worse]["final"]["psnr"]
            checks.append({"claim": f"{by_suffix[better]['name']} > {by_suffix[worse]['name']}",
                           "psnr": [high, low], "holds": high > low})
    return checks


@dataclass(frozen=True)
class Variant:
    name: str
    preset: str
    overrides: tuple[str, ...]

    @classmethod
    def parse(cls, text: str) -> "Variant":
        name, sep, spec = text.partition("=")
        if not sep:
            return cls(text, text, ())
        preset, *overrides = spec.split("+")
        return cls(name, preset, tuple(overrides))
