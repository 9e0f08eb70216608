"""Points along a training curve and what a curve says: when it reached a PSNR."""

from __future__ import annotations

THRESHOLDS_DB = (20.0, 25.0, 30.0)


def curve_points(budget_seconds: float | None, iterations: int | None, points: int) -> list[float]:
    """The training budgets (seconds or iterations) at which a variant's curve is scored."""
    total = budget_seconds if budget_seconds is not None else iterations
    # Denser early, where the curves move: quadratic spacing.
    return sorted({round(total * ((k + 1) / points) ** 2, 3) for k in range(points)})


def time_to_reach(curve: list[dict], threshold: float) -> float | None:
    """Training seconds at which PSNR first reaches ``threshold`` (linear between points)."""
    previous = {"train_seconds": 0.0, "psnr": 0.0}
    for point in curve:
        if point["psnr"] >= threshold:
            span = point["psnr"] - previous["psnr"]
            fraction = 1.0 if span <= 0 else (threshold - previous["psnr"]) / span
            return previous["train_seconds"] + fraction * (point["train_seconds"] - previous["train_seconds"])
        previous = point
    return None
