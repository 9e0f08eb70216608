"""``bench --budget-seconds 60,120,300,600,1800``: the speed/accuracy trade across budgets.

Each budget is benched on its own, as a suite (``run_suite`` into ``BENCH/<budget>s``): every
variant trains from scratch for that budget, as ``train --max-seconds`` would, so its schedule
(learning-rate decay, grid growth, ``auto``'s choices) fits the budget, which a point along a
longer run's curve does not. The folders resume budget by budget and scene by scene (a matrix of
presets, budgets and scenes takes hours: stop it and run the same command again).
``BENCH/trade.{json,md,png}`` then hold, for each scene, each variant's test PSNR at each budget
beside its rays and samples a second, the best fixed variant (any whose preset is not ``auto``)
at each budget, and ``auto``'s gap to it.
"""

from __future__ import annotations

import sys
from pathlib import Path

from ..core.devices import machine_record, resolve_device
from ..core.errors import NerfError
from ..core.files import write_json
from ..core.provenance import provenance
from .curves import curve_points
from .suite import run_suite
from .tables import plot_trade, trade_markdown
from .variants import Variant


def budget_folder(out_dir: Path, seconds: float) -> Path:
    """Where one budget's suite bench lives.

    Example:
        >>> budget_folder(Path("BENCH"), 120.0).as_posix(), budget_folder(Path("BENCH"), 1.5).as_posix()
        ('BENCH/120s', 'BENCH/1.5s')
    """
    return out_dir / f"{seconds:g}s"


def trade_summary(summaries: dict[float, dict]) -> dict:
    """Each scene's variants across the budgets, from each budget's suite summary
    (``run_suite``'s, keyed by the budget in seconds, whose scenes name their best fixed variant
    and auto's gap to it): pure, no I/O.

    Example:
        >>> row = lambda name, psnr: {"variant": name, "preset": name, "psnr": psnr, "ssim": 0.9,
        ...     "iterations": 10, "rays_per_second": 1e4, "samples_per_second": 1e6}
        >>> suite = lambda fast, auto: {"scenes": [{"scene": "lego", "variants": [row("fast", fast), row("auto", auto)],
        ...     "best_fixed": {"variant": "fast", "psnr": fast},
        ...     "auto": {"variant": "auto", "psnr": auto, "gap_to_best_fixed_db": auto - fast}}]}
        >>> trade = trade_summary({600.0: suite(33.0, 32.5), 60.0: suite(30.0, 31.5)})
        >>> scene = trade["scenes"][0]
        >>> [(b["budget_seconds"], b["auto"]["gap_to_best_fixed_db"]) for b in scene["budgets"]]
        [(60.0, 1.5), (600.0, -0.5)]
        >>> scene["variants"][1]["by_budget"]["600"]["psnr"]
        32.5
    """
    budgets = sorted(summaries)
    names = [scene["scene"] for scene in summaries[budgets[0]]["scenes"]]
    scenes = []
    for name in names:
        variants: dict[str, dict] = {}
        per_budget = []
        for budget in budgets:
            scene = next((s for s in summaries[budget]["scenes"] if s["scene"] == name), {})
            for row in scene.get("variants", []):
                entry = variants.setdefault(row["variant"], {"variant": row["variant"], "preset": row["preset"],
                                                             "by_budget": {}})
                entry["by_budget"][f"{budget:g}"] = {key: row.get(key) for key in (
                    "psnr", "ssim", "iterations", "rays_per_second", "samples_per_second")}
            per_budget.append({"budget_seconds": budget, "best_fixed": scene.get("best_fixed"),
                               "auto": scene.get("auto")})
        scenes.append({"scene": name, "variants": list(variants.values()), "budgets": per_budget})
    return {"budgets_seconds": budgets, "scenes": scenes}


def run_trade(paths: list[Path], variants: list[Variant], out_dir: Path, budgets: tuple[float, ...],
              points: int | tuple[float, ...] = 1, curve_views: int = 8, seed: int = 0, device: str = "auto",
              overwrite: bool = False, command: str | None = None) -> dict:
    """Bench ``variants`` on every dataset of ``paths`` at each of ``budgets`` (seconds), each
    budget into ``budget_folder(out_dir, budget)``, and write ``trade.{json,md,png}``; return
    the trade summary."""
    budgets = tuple(sorted(set(budgets)))
    for budget in budgets:  # refused before anything trains, not after the first budgets
        try:
            curve_points(budget, None, points)
        except ValueError as exc:
            raise NerfError(f"bench --points: {exc} (budget {budget:g} s)") from None
    if out_dir.exists() and not out_dir.is_dir():
        raise NerfError(f"{out_dir}: exists and is not a folder")
    summaries = {}
    for number, budget in enumerate(budgets, 1):
        folder = budget_folder(out_dir, budget)
        print(f"bench: budget {number}/{len(budgets)}, {budget:g} s, into {folder}", file=sys.stderr, flush=True)
        summaries[budget] = run_suite(paths, variants, folder, budget, None, points=points, curve_views=curve_views,
                                      seed=seed, device=device, overwrite=overwrite, command=command)
    trade = {**trade_summary(summaries), "seed": seed, "device": device,
             "machine": machine_record(resolve_device(device)), "provenance": provenance(command),
             "budget_folders": {f"{b:g}": str(budget_folder(out_dir, b)) for b in budgets}}
    write_json(out_dir / "trade.json", trade)
    (out_dir / "trade.md").write_text(trade_markdown(trade))
    plot_trade(trade, out_dir / "trade.png")
    return trade
