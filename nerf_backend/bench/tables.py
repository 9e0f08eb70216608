"""What a bench writes for people: the markdown table and the PSNR-against-time plot."""

from __future__ import annotations

import math
from pathlib import Path

from ..core.devices import machine_words
from ..core.plotting import pyplot
from ..core.provenance import provenance_line
from .curves import THRESHOLDS_DB


def _fmt(value: float | None, spec: str) -> str:
    return "—" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def markdown_table(report: dict) -> str:
    budget = report["budget"]
    # Geometry columns only when the dataset has a true surface (datasets_gen's scene_geometry.ply).
    geometry = report.get("geometry")
    lines = [
        f"Budget: {budget.get('seconds', budget.get('iterations'))} "
        f"{'training seconds' if 'seconds' in budget else 'iterations'} per variant, seed {report['seed']}, "
        f"{machine_words(report['machine'])}. "
        f"{provenance_line(report.get('provenance'))}".rstrip(),
        "",
        "| variant | iterations | rays/s | M samples/s | test PSNR (dB) | SSIM | s to 20 / 25 / 30 dB "
        "| render s/image | peak MB | model MB |" + (" Chamfer | F-score at τ |" if geometry else ""),
        "| --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: |" + (" ---: | ---: |" if geometry else ""),
    ]
    for v in report["variants"]:
        final = v["final"]
        reach = " / ".join(_fmt(v["time_to_psnr_s"][f"{t:g}"], ".0f") for t in THRESHOLDS_DB)
        shape = f" {_fmt(final.get('chamfer'), '.4f')} | {_fmt(final.get('f_score'), '.3f')} |"
        samples = final.get("samples_per_second")
        lines.append(f"| {v['name']} | {final['iterations']} | {_fmt(final.get('rays_per_second'), '.0f')} "
                     f"| {_fmt(None if samples is None else samples / 1e6, '.2f')} | {final['psnr']:.2f} "
                     f"| {final['ssim']:.4f} | {reach} | {v['render_seconds_per_image']:.2f} | {v['peak_memory_mb']:.0f} "
                     f"| {v['model_size_mb']:.1f} |" + (shape if geometry else ""))
    if geometry:
        lines += ["", f"Geometry: each variant's mesh (eval --geometry, resolution {geometry['mesh_resolution']}) "
                      f"against the scene's true surface ({geometry['truth']}); Chamfer distance in the dataset's "
                      f"units; F-score at τ = {geometry['tau']:.4g}, {geometry['tau_rule']}."]
        lines += [f"- {v['name']}: no geometry: {v['final']['geometry_unavailable']}"
                  for v in report["variants"] if v["final"].get("geometry_unavailable")]
    if report.get("ablation_order"):
        lines += ["", "Ablations against the NeRF paper's order (its Table 2):", ""]
        for check in report["ablation_order"]:
            lines.append(f"- {check['claim']}: {check['psnr'][0]:.2f} vs {check['psnr'][1]:.2f} dB — "
                         f"{'agrees' if check['holds'] else 'does not agree'} with the paper")
    return "\n".join(lines) + "\n"


def plot_curves(report: dict, path: Path) -> None:
    plt = pyplot()

    figure, axis = plt.subplots(figsize=(7, 4.5), dpi=120)
    for v in report["variants"]:
        xs = [0.0] + [p["train_seconds"] for p in v["curve"]]
        ys = [float("nan")] + [p["psnr"] for p in v["curve"]]
        axis.plot(xs, ys, marker="o", label=v["name"])
    for t in THRESHOLDS_DB:
        axis.axhline(t, color="grey", linewidth=0.5, linestyle=":")
    axis.set_xlabel("training time (s)")
    axis.set_ylabel("test PSNR (dB)")
    axis.set_title("Speed / accuracy: PSNR against training time")
    axis.grid(alpha=0.3)
    axis.legend()
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def suite_markdown(summary: dict) -> str:
    """The suite's summary: a row per scene and variant, then each scene's best fixed variant
    and auto's gap to it."""
    budget = summary["budget"]
    lines = [
        f"Budget: {budget.get('seconds', budget.get('iterations'))} "
        f"{'training seconds' if 'seconds' in budget else 'iterations'} per variant and scene, seed {summary['seed']}, "
        f"{machine_words(summary['machine'])}. Blank: the PSNR of an "
        "all-white image against the test views. Collapse: detected by the trainer (a `collapse` event) / final "
        f"PSNR within {summary['collapse_margin_db']:g} dB of the blank image's. "
        f"{provenance_line(summary.get('provenance'))}".rstrip(),
        "",
        "| scene | variant | test PSNR (dB) | SSIM | s to 25 / 30 dB | s/iteration | iterations | blank PSNR (dB) "
        "| collapse detected / final |",
        "| --- | --- | ---: | ---: | --- | ---: | ---: | ---: | --- |",
    ]
    for scene in summary["scenes"]:
        for row in scene["variants"]:
            reach = " / ".join(_fmt(row[f"time_to_{t}_db_s"], ".0f") for t in ("25", "30"))
            collapse = f"{'yes' if row['collapse_detected'] else 'no'} / {'yes' if row['collapsed'] else 'no'}"
            lines.append(f"| {scene['scene']} | {row['variant']} | {row['psnr']:.2f} | {row['ssim']:.4f} | {reach} "
                         f"| {_fmt(row['seconds_per_iteration'], '.3f')} | {row['iterations']} "
                         f"| {_fmt(row['blank_psnr'], '.2f')} | {collapse} |")
    lines += ["", "| scene | best fixed variant | its PSNR (dB) | auto PSNR (dB) | auto − best fixed (dB) |",
              "| --- | --- | ---: | ---: | ---: |"]
    for scene in summary["scenes"]:
        best, auto = scene["best_fixed"] or {}, scene["auto"] or {}
        lines.append(f"| {scene['scene']} | {best.get('variant', '—')} | {_fmt(best.get('psnr'), '.2f')} "
                     f"| {_fmt(auto.get('psnr'), '.2f')} | {_fmt(auto.get('gap_to_best_fixed_db'), '+.2f')} |")
    return "\n".join(lines) + "\n"


def plot_suite(summary: dict, path: Path) -> None:
    """Final test PSNR per scene and variant (bars), the blank image's PSNR per scene (a black
    line across its bars); a collapsed variant's bar is hatched."""
    plt = pyplot()
    # matplotlib is deferred on purpose (core/plotting.py): loaded by pyplot() above.
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    scenes = summary["scenes"]
    names = [v["name"] for v in summary["variants"]]
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    width = 0.8 / max(1, len(names))
    figure, axis = plt.subplots(figsize=(max(7.0, 1.3 * len(scenes) + 3), 4.5), dpi=120)
    for k, name in enumerate(names):
        for i, scene in enumerate(scenes):
            row = next((r for r in scene["variants"] if r["variant"] == name), None)
            if row is not None:
                axis.bar(i - 0.4 + width * (k + 0.5), row["psnr"], width, color=colours[k % len(colours)],
                         hatch="//" if row["collapsed"] else None)
    for i, scene in enumerate(scenes):
        if scene["blank_psnr"] is not None:
            axis.hlines(scene["blank_psnr"], i - 0.45, i + 0.45, color="black", linewidth=1.5)
    handles = [Patch(color=colours[k % len(colours)], label=name) for k, name in enumerate(names)]
    handles += [Patch(facecolor="white", edgecolor="black", hatch="//", label="collapsed"),
                Line2D([], [], color="black", linewidth=1.5, label="blank image")]
    axis.set_xticks(range(len(scenes)))
    axis.set_xticklabels([scene["scene"] for scene in scenes], rotation=20, ha="right")
    axis.set_ylabel("final test PSNR (dB)")
    axis.set_title("Final test PSNR per scene and variant, at equal budget")
    axis.grid(axis="y", alpha=0.3)
    axis.legend(handles=handles, fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0))
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def _rate_words(cell: dict) -> str:
    """A trade table's cell: PSNR, then thousands of rays and millions of samples a second."""
    rays, samples = cell.get("rays_per_second"), cell.get("samples_per_second")
    return (f"{cell['psnr']:.2f} · {_fmt(None if rays is None else rays / 1e3, '.1f')} · "
            f"{_fmt(None if samples is None else samples / 1e6, '.2f')}")


def trade_markdown(trade: dict) -> str:
    """The trade across budgets: each scene's variants at each budget (PSNR beside rays and
    samples a second), then the best fixed variant at each budget and auto's gap to it."""
    budgets = [f"{b:g}" for b in trade["budgets_seconds"]]
    lines = [
        f"Each budget trained from scratch (`train --max-seconds`), seed {trade['seed']}, "
        f"{machine_words(trade['machine'])}. A cell: final test PSNR (dB) · thousands of rays a second · "
        f"millions of samples a second the field was trained at. {provenance_line(trade.get('provenance'))}".rstrip(),
        "",
        "| scene | variant | " + " | ".join(f"{b} s" for b in budgets) + " |",
        "| --- | --- | " + " | ".join("---:" for _ in budgets) + " |",
    ]
    for scene in trade["scenes"]:
        for variant in scene["variants"]:
            cells = [_rate_words(variant["by_budget"][b]) if b in variant["by_budget"] else "—" for b in budgets]
            lines.append(f"| {scene['scene']} | {variant['variant']} | " + " | ".join(cells) + " |")
    lines += ["", "| scene | budget | best fixed variant | its PSNR (dB) | auto PSNR (dB) | auto − best fixed (dB) |",
              "| --- | ---: | --- | ---: | ---: | ---: |"]
    for scene in trade["scenes"]:
        for row in scene["budgets"]:
            best, auto = row["best_fixed"] or {}, row["auto"] or {}
            lines.append(f"| {scene['scene']} | {row['budget_seconds']:g} s | {best.get('variant', '—')} "
                         f"| {_fmt(best.get('psnr'), '.2f')} | {_fmt(auto.get('psnr'), '.2f')} "
                         f"| {_fmt(auto.get('gap_to_best_fixed_db'), '+.2f')} |")
    return "\n".join(lines) + "\n"


def plot_trade(trade: dict, path: Path) -> None:
    """Final test PSNR against the training budget (log scale), a line per variant, a panel per scene."""
    plt = pyplot()
    scenes = trade["scenes"]
    columns = min(3, len(scenes))
    rows = -(-len(scenes) // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns + 1.5, 3.4 * rows), dpi=120, squeeze=False)
    for axis, scene in zip(axes.flat, scenes):
        for variant in scene["variants"]:
            points = sorted((float(b), cell["psnr"]) for b, cell in variant["by_budget"].items())
            axis.plot([b for b, _ in points], [p for _, p in points], marker="o", label=variant["variant"])
        axis.set_xscale("log")
        axis.minorticks_off()  # the budgets alone are labelled
        axis.set_xticks(trade["budgets_seconds"])
        axis.set_xticklabels([f"{b:g}" for b in trade["budgets_seconds"]])
        axis.set_title(scene["scene"])
        axis.set_xlabel("training budget (s)")
        axis.set_ylabel("test PSNR (dB)")
        axis.grid(alpha=0.3)
    for axis in list(axes.flat)[len(scenes):]:
        axis.set_visible(False)
    axes.flat[0].legend(fontsize="small")
    figure.suptitle("Speed / accuracy: each budget trained from scratch")
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
