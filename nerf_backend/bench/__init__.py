"""``python -m nerf_backend bench``: the speed/accuracy trade of several presets, measured
on the same dataset, seed and budget in one run.

Each preset trains in its own child process (so its peak memory is its own) in segments:
train up to the next point in time (or iteration), score a fixed subset of test views,
resume. Scoring time is not training time. At the end every test view is rendered and
scored, and render seconds per image, peak memory and model size are recorded. Results:
``bench.json``, ``bench.md`` (a table) and ``bench.png`` (PSNR against training time).

A variant is a preset with changes: ``NAME=PRESET+KEY=VALUE+...`` (``--set`` syntax), e.g.
``no_pe=paper+field.position_frequencies=0+field.direction_frequencies=0``.

``bench --suite`` does this on every dataset of a folder and summarises across the scenes;
``bench --budget-seconds 60,120,300`` does it at each budget from scratch and writes the trade
across them.

One idea a module: ``variants`` (variants and the paper's ablations), ``curves`` (curve points,
time to a PSNR), ``runner`` (one dataset: ``run_bench``), ``suite`` (many datasets:
``run_suite``), ``trade`` (several budgets: ``run_trade``), ``tables`` (markdown tables and plots), ``step_cost`` (``bench-step`` of a NeRF
preset), ``plain_nerf`` (the plain NeRF step it measures against), ``step_profile``
(``bench-step`` of a marched preset: stages against the machine) and ``hardware`` (the
machine's measured FLOP rate, bandwidth and gather rate).

Layer 7: above training and evaluation, which it drives.
"""

from .curves import THRESHOLDS_DB, curve_points, time_to_reach
from .hardware import measure_hardware
from .runner import bench_variant, run_bench
from .step_cost import step_cost
from .step_profile import profile_marched_step, profile_markdown
from .suite import COLLAPSE_MARGIN_DB, find_datasets, run_suite, scene_blank_psnr
from .tables import markdown_table, plot_curves, plot_suite, plot_trade, suite_markdown, trade_markdown
from .trade import budget_folder, run_trade, trade_summary
from .variants import ABLATIONS, DEFAULT_PRESETS, PAPER_ORDER, Variant, ablation_order, ablation_variants

__all__ = [
    "ABLATIONS", "COLLAPSE_MARGIN_DB", "DEFAULT_PRESETS", "PAPER_ORDER", "THRESHOLDS_DB", "Variant",
    "ablation_order", "ablation_variants", "bench_variant", "budget_folder", "curve_points", "find_datasets",
    "markdown_table", "measure_hardware", "plot_curves", "plot_suite", "plot_trade", "profile_marched_step",
    "profile_markdown", "run_bench", "run_suite", "run_trade", "scene_blank_psnr", "step_cost",
    "suite_markdown", "time_to_reach", "trade_markdown", "trade_summary",
]
