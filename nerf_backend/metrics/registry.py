"""Every image metric the project reports, in one list that eval, compare, the report, the
bench and the add-on all read (the add-on through the ``metrics`` table written into each
metrics.json and compare.json). A new metric is one ``Metric`` here.

Example:
    >>> import numpy as np
    >>> tools = MetricTools(lpips=None, lpips_unavailable="no weights")
    >>> scores = score_image(np.zeros((16, 16, 3)), np.full((16, 16, 3), 0.1), tools)
    >>> round(scores["psnr"], 2), scores["lpips"]
    (20.0, None)
    >>> METRICS_BY_KEY["psnr"].format(scores["psnr"])
    '20.00 dB'
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .image_metrics import psnr, ssim
from .lpips_metric import Lpips, lpips_distance


@dataclass(frozen=True)
class MetricTools:
    """What some metrics need beyond the two images: the LPIPS network, or why there is none."""

    lpips: Lpips | None = None
    lpips_unavailable: str | None = None


@dataclass(frozen=True)
class Metric:
    key: str  # the key in metrics.json, compare.json and bench.json
    label: str
    unit: str
    higher_is_better: bool
    decimals: int
    # (rendered, reference, tools) -> value, or None when the metric cannot be computed.
    compute: Callable[[np.ndarray, np.ndarray, MetricTools], float | None]
    # Why the value is None (tools -> reason), for metrics that can be unavailable.
    unavailable: Callable[[MetricTools], str | None] = lambda tools: None

    def format(self, value: float | None) -> str:
        if value is None:
            return "unavailable"
        return f"{value:.{self.decimals}f}" + (f" {self.unit}" if self.unit else "")

    def describe(self) -> dict:
        """The metric as the add-on and the report read it from a results file."""
        return {"key": self.key, "label": self.label, "unit": self.unit,
                "higher_is_better": self.higher_is_better, "decimals": self.decimals}


METRICS: tuple[Metric, ...] = (
    Metric("psnr", "PSNR", "dB", True, 2, lambda a, b, tools: psnr(a, b)),
    Metric("ssim", "SSIM", "", True, 4, lambda a, b, tools: ssim(a, b)),
    Metric("lpips", "LPIPS", "", False, 4,
           lambda a, b, tools: None if tools.lpips is None else lpips_distance(tools.lpips, a, b),
           unavailable=lambda tools: None if tools.lpips is not None else (tools.lpips_unavailable or "not computed")),
)
METRICS_BY_KEY: dict[str, Metric] = {metric.key: metric for metric in METRICS}


def score_image(rendered: np.ndarray, reference: np.ndarray, tools: MetricTools,
                metrics: tuple[Metric, ...] = METRICS) -> dict[str, float | None]:
    """Every metric of ``rendered`` against ``reference`` (``H×W×3`` floats in [0, 1])."""
    return {metric.key: metric.compute(rendered, reference, tools) for metric in metrics}


def mean_scores(per_view: list[dict], metrics: tuple[Metric, ...] = METRICS) -> dict[str, float | None]:
    """Each metric's mean over the views that have a value (None if none has)."""
    means: dict[str, float | None] = {}
    for metric in metrics:
        values = [view[metric.key] for view in per_view if view.get(metric.key) is not None]
        means[metric.key] = float(np.mean(values)) if values else None
    return means


def unavailable_reasons(tools: MetricTools, metrics: tuple[Metric, ...] = METRICS) -> dict[str, str]:
    """``{key}_unavailable`` for each metric that has no value with these tools."""
    reasons = {f"{metric.key}_unavailable": metric.unavailable(tools) for metric in metrics}
    return {key: reason for key, reason in reasons.items() if reason is not None}


def summary_line(scores: dict, metrics: tuple[Metric, ...] = METRICS, separator: str = ", ") -> str:
    """``PSNR 31.20 dB, SSIM 0.9512, LPIPS unavailable``."""
    return separator.join(f"{metric.label} {metric.format(scores.get(metric.key))}" for metric in metrics)
