"""Points along a training curve and what a curve says: when it reached a PSNR."""

from __future__ import annotations

THRESHOLDS_DB = (20.0, 25.0, 30.0)


def curve_points(budget_seconds: float | None, iterations: int | None, points: int | tuple[float, ...]) -> list[float]:
    """The training budgets (seconds or iterations) at which a variant's curve is scored:
    ``points`` of them spaced quadratically (denser early, where the curves move), or those
    given (a tuple, each within the budget), ending with the whole budget.

    Example:
        >>> curve_points(600, None, 3), curve_points(600, None, (60, 120, 300))
        ([66.667, 266.667, 600.0], [60, 120, 300, 600])
    """
    total = budget_seconds if budget_seconds is not None else iterations
    if isinstance(points, tuple):
        if any(not 0 < point <= total for point in points):
            raise ValueError(f"curve points {', '.join(f'{p:g}' for p in points)} must lie within the budget "
                             f"({total:g})")
        return sorted({*points, total})
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
