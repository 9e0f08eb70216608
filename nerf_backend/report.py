"""``python -m nerf_backend report``: a self-contained HTML page comparing NeRF renders with
Cycles ground truth.

``report RUN`` writes ``RUN/report/index.html`` with its images beside it (no network, no
external scripts or styles): the headline metrics and what the run cost, the scene
decisions ``auto`` made, every test view (ground truth, render, error heatmap, metrics;
sortable, worst first; click a picture for full size), the training curves, and the bench
results when the run sits inside a bench folder. ``report A B ...`` compares several
results on the same dataset: metrics side by side and the same views from each. A result
is a run folder, or a folder of another tool's renders scored by
``eval --dataset D --renders DIR`` (its ``metrics.json`` says which dataset).
"""

from __future__ import annotations

import html
import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .dataset import load_split
from .error_images import ERROR_COLOURMAP, ERROR_SCALE, error_heatmap
from .errors import NerfError
from .evaluate import METRICS_NAME, read_rgb
from .files import write_png
from .run_folder import RunFolder

COMPARED_VIEWS = 6


@dataclass
class Result:
    """One evaluated set of renders: a run's, or another tool's."""

    label: str
    path: Path
    metrics: dict
    renders_dir: Path
    dataset: Path
    run_config: dict | None  # config.json of a run; None for other tools' renders
    events: list[dict]

    @property
    def by_view(self) -> dict[str, dict]:
        return {v["view"]: v for v in self.metrics["per_view"]}


def load_result(path: Path, split: str) -> Result:
    """A run folder (evaluated now if its metrics are missing or stale) or a folder with
    ``metrics.json`` written by ``eval --dataset D --renders DIR``."""
    from .devices import resolve_device
    from .evaluate import evaluate_run
    from .inference import renders_are_current

    path = Path(path)
    if (path / "config.json").is_file():
        run = RunFolder(path)
        metrics_path = path / METRICS_NAME
        metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else None
        if metrics is None or metrics.get("split") != split or not renders_are_current(run, split) or "renders" not in metrics:
            metrics = evaluate_run(path, split, resolve_device("auto"), progress=False)
        return Result(_label(path), path, metrics, Path(metrics["renders"]), Path(metrics["dataset"]),
                      run.read_config(), run.read_events())
    metrics_path = path / METRICS_NAME
    if not metrics_path.is_file():
        raise NerfError(f"{path}: neither a run folder (no config.json) nor scored renders (no {METRICS_NAME}); "
                        f"score renders first with: python -m nerf_backend eval --dataset DATASET --renders {path}")
    metrics = json.loads(metrics_path.read_text())
    for key in ("dataset", "renders", "per_view"):
        if key not in metrics:
            raise NerfError(f"{metrics_path}: no {key!r}; re-score with python -m nerf_backend eval --dataset DATASET --renders DIR")
    return Result(_label(path), path, metrics, Path(metrics["renders"]), Path(metrics["dataset"]), None, [])


def _label(path: Path) -> str:
    """``parent/name``: run folders are often named alike (run, renders)."""
    resolved = path.resolve()
    return f"{resolved.parent.name}/{resolved.name}" if resolved.parent.name else resolved.name


def _fmt(value: float | None, spec: str, missing: str = "—") -> str:
    return missing if value is None else format(value, spec)


def _short(value) -> str:
    """A decision's value for people: floats to 3 decimals, strings as they are."""
    def rounded(v):
        if isinstance(v, float):
            return round(v, 3)
        if isinstance(v, dict):
            return {k: rounded(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [rounded(x) for x in v]
        return v
    return value if isinstance(value, str) else json.dumps(rounded(value))


def _plot_error_scale(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(4.0, 0.9), dpi=100)
    axis.imshow(np.linspace(0, 1, 256)[None, :], aspect="auto", cmap=ERROR_COLOURMAP, extent=(0, ERROR_SCALE, 0, 1))
    axis.set_yticks([])
    axis.set_xlabel("mean |render − ground truth| per pixel (RGB in [0, 1])", fontsize=7)
    axis.tick_params(labelsize=7)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def _plot_training(events: list[dict], path: Path) -> bool:
    """Loss and PSNR against iterations and against training seconds; False if no events."""
    train = [e for e in events if e.get("event") == "train"]
    val = [e for e in events if e.get("event") == "val"]
    if not train:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(2, 2, figsize=(9, 6), dpi=100)
    for column, (key, label) in enumerate((("iteration", "iteration"), ("elapsed_s", "training time (s)"))):
        loss_axis, psnr_axis = axes[0, column], axes[1, column]
        loss_axis.plot([e[key] for e in train], [e["loss"] for e in train], linewidth=0.8)
        loss_axis.set_yscale("log")
        loss_axis.set_ylabel("training loss (MSE)")
        psnr_axis.plot([e[key] for e in train], [e["psnr"] for e in train], linewidth=0.8, label="training batch")
        if val:
            psnr_axis.plot([e[key] for e in val], [e["psnr"] for e in val], marker="o", label="validation view")
            blank = [e for e in val if e.get("blank_psnr") is not None and math.isfinite(e["blank_psnr"])]
            if blank:  # what an empty model scores on the same views: the collapse guard's floor
                psnr_axis.plot([e[key] for e in blank], [e["blank_psnr"] for e in blank], linestyle="--",
                               color="grey", linewidth=0.8, label="blank image, same view")
        for event in (e for e in events if e.get("event") == "collapse" and key in e):
            psnr_axis.axvline(event[key], color="#c0392b", linewidth=0.8)  # where the guard found a collapse
        psnr_axis.set_ylabel("PSNR (dB)")
        psnr_axis.legend(fontsize=8)
        for axis in (loss_axis, psnr_axis):
            axis.set_xlabel(label)
            axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
    return True


def _find_bench(path: Path) -> Path | None:
    """``bench.json`` in the run folder or the bench folder holding it (BENCH/runs/NAME)."""
    for folder in (path, path.parent, path.parent.parent):
        if (folder / "bench.json").is_file():
            return folder / "bench.json"
    return None


STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1200px; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; } td, th { padding: 0.25em 0.6em; border-bottom: 1px solid #eee;
  text-align: left; vertical-align: middle; }
th.sortable { cursor: pointer; color: #0645ad; } .num { text-align: right; font-variant-numeric: tabular-nums; }
.headline { display: flex; gap: 1em; flex-wrap: wrap; } .card { background: #f4f6f8; padding: 0.6em 1em; border-radius: 6px; }
.card b { display: block; font-size: 1.4em; } .muted { color: #666; font-size: 0.9em; }
img.wide { width: 100%; max-width: 900px; display: block; }
img.thumb { width: 128px; height: auto; image-rendering: pixelated; border: 1px solid #ddd; display: block; }
figure { margin: 0; } figcaption { font-size: 0.75em; color: #555; }
.alert { background: #fdecea; border-left: 4px solid #c0392b; padding: 0.5em 1em; margin: 1em 0; }
"""

# Depth is the distance along each ray in the dataset's frame (after its world_to_nerf).
DEPTH_UNIT = "dataset units"
DEPTH_UNIT_NOTE = "mean absolute error of the distance along each ray, in the dataset's frame (after world_to_nerf)"

SORT_SCRIPT = """
document.querySelectorAll("table.views").forEach(function (table) {
  table.querySelectorAll("th.sortable").forEach(function (header) {
    header.addEventListener("click", function () {
      var key = header.dataset.key, body = table.tBodies[0];
      var ascending = header.dataset.order !== "asc";
      header.dataset.order = ascending ? "asc" : "desc";
      var rows = Array.prototype.slice.call(body.rows);
      rows.sort(function (a, b) {
        var x = parseFloat(a.dataset[key]), y = parseFloat(b.dataset[key]);
        if (isNaN(x)) x = Infinity; if (isNaN(y)) y = Infinity;
        return ascending ? x - y : y - x;
      });
      rows.forEach(function (row) { body.appendChild(row); });
    });
  });
});
window.addEventListener("load", function () {
  var broken = Array.prototype.filter.call(document.images, function (img) { return !img.complete || img.naturalWidth === 0; });
  document.body.dataset.imagesLoaded = String(document.images.length - broken.length);
  document.body.dataset.imagesBroken = String(broken.length);
});
"""


class _Page:
    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.images = out_dir / "images"
        self.parts: list[str] = []

    def add(self, markup: str) -> None:
        self.parts.append(markup)

    def image(self, name: str, pixels: np.ndarray | None = None, source: Path | None = None) -> str:
        """Write (or copy) an image next to the page; returns its relative path."""
        target = self.images / name
        if pixels is not None:
            write_png(target, pixels)
        elif source is not None:
            shutil.copyfile(source, target)
        return f"images/{name}"

    def figure(self, relative: str, caption: str, kind: str = "thumb") -> str:
        return (f'<figure><a href="{html.escape(relative)}" target="_blank"><img class="{kind}" src="{html.escape(relative)}" '
                f'alt="{html.escape(caption)}"></a><figcaption>{html.escape(caption)}</figcaption></figure>')

    def write(self, title: str) -> Path:
        document = (f'<!DOCTYPE html>\n{MARKER}\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
                    f"<style>{STYLE}</style></head><body>\n" + "\n".join(self.parts)
                    + f"\n<script>{SORT_SCRIPT}</script></body></html>\n")
        path = self.out_dir / "index.html"
        path.write_text(document, encoding="utf-8")
        return path


def _headline(result: Result) -> str:
    m = result.metrics
    cards = [("PSNR", f"{m['psnr']:.2f} dB"), ("SSIM", f"{m['ssim']:.4f}"),
             ("LPIPS", _fmt(m.get("lpips"), ".4f", "unavailable"))]
    if m.get("depth_mae") is not None:
        cards.append(("depth MAE", f"{m['depth_mae']:.4f} {DEPTH_UNIT}"))
    config, events = result.run_config, result.events
    if config is not None:
        done = [e for e in events if e.get("event") in ("done", "checkpoint")]
        last = done[-1] if done else {}
        cards += [("preset", config["preset"]), ("iterations", str(last.get("iteration", "—"))),
                  ("training time", _fmt(last.get("elapsed_s"), ".1f") + " s"), ("device", config.get("device", "—"))]
    out = ['<div class="headline">'] + [f'<div class="card">{html.escape(k)}<b>{html.escape(v)}</b></div>' for k, v in cards]
    out.append("</div>")
    out += _collapse_alerts(events)
    notes = [f"{m['views']} {m['split']} views. Background: {m['background']}."]
    if m.get("lpips") is None:
        notes.append(f"LPIPS unavailable: {m.get('lpips_unavailable')}.")
    else:
        notes.append(f"LPIPS: {m.get('lpips_net')}.")
    notes.append(f"Depth error: {m['depth_mask']}." if m.get("depth_mae") is not None
                 else f"Depth error unavailable: {m.get('depth_unavailable')}.")
    out.append("".join(f'<p class="muted">{html.escape(n)}</p>' for n in notes))
    if config is not None and config.get("decisions"):
        out.append("<h3>What the run decided about the scene</h3><table><tr><th>decision</th><th>value</th><th>reason</th></tr>")
        for name, decision in config["decisions"].items():
            value = decision.get("value", {k: v for k, v in decision.items() if k != "reason"})
            out.append(f"<tr><td>{html.escape(name)}</td><td>{html.escape(_short(value))}"
                       f"</td><td>{html.escape(str(decision.get('reason', '')))}</td></tr>")
        out.append("</table>")
    return "\n".join(out)


def _collapse_alerts(events: list[dict]) -> list[str]:
    """What the collapse guard found during training and what the trainer did about it."""
    alerts = []
    for event in (e for e in events if e.get("event") == "collapse"):
        verdict = "The run failed: " if event.get("final") else "The run collapsed and was restarted: "
        alerts.append(f'<div class="alert"><b>{html.escape(verdict)}</b>'
                      f'{html.escape(str(event.get("reason", "")))}. What the trainer did: '
                      f'{html.escape(str(event.get("action", "")))}.</div>')
    return alerts


def _views_table(page: _Page, result: Result, prefix: str, split) -> str:
    rows = []
    stems = [p.stem for p in split.image_paths]
    per_view = sorted(result.metrics["per_view"], key=lambda v: v["psnr"])  # worst first
    for view in per_view:
        index = stems.index(view["view"])
        reference = split.rgb_on_white(index).numpy()
        rendered = read_rgb(result.renders_dir / f"{view['view']}.png")
        gt = page.image(f"gt_{view['view']}.png", pixels=reference)
        render = page.image(f"{prefix}_{view['view']}.png", source=result.renders_dir / f"{view['view']}.png")
        error = page.image(f"{prefix}_{view['view']}_error.png", pixels=error_heatmap(rendered, reference))
        data = " ".join(f'data-{k}="{_fmt(view.get(k), ".6f", "nan")}"' for k in ("psnr", "ssim", "lpips", "depth_mae"))
        rows.append(
            f'<tr {data} data-name="{index}"><td>{html.escape(view["view"])}</td><td>{page.figure(gt, "Cycles")}</td>'
            f"<td>{page.figure(render, 'NeRF')}</td><td>{page.figure(error, 'error')}</td>"
            f'<td class="num">{view["psnr"]:.2f}</td><td class="num">{view["ssim"]:.4f}</td>'
            f'<td class="num">{_fmt(view.get("lpips"), ".4f")}</td><td class="num">{_fmt(view.get("depth_mae"), ".4f")}</td></tr>')
    header = ('<table class="views"><thead><tr><th class="sortable" data-key="name">view</th><th>Cycles (ground truth)</th>'
              '<th>NeRF</th><th>error</th><th class="sortable num" data-key="psnr" data-order="asc">PSNR (dB)</th>'
              '<th class="sortable num" data-key="ssim">SSIM</th><th class="sortable num" data-key="lpips">LPIPS</th>'
              f'<th class="sortable num" data-key="depth_mae" title="{DEPTH_UNIT_NOTE}">depth MAE ({DEPTH_UNIT})</th>'
              "</tr></thead><tbody>")
    return header + "\n".join(rows) + "</tbody></table>"


def _bench_section(page: _Page, bench_json: Path) -> str:
    bench = json.loads(bench_json.read_text())
    out = ["<h2>Speed and accuracy of the presets (bench)</h2>"]
    if (bench_json.parent / "bench.png").is_file():
        out.append(page.figure(page.image("bench.png", source=bench_json.parent / "bench.png"),
                               "PSNR against training time", kind="wide"))
    out.append('<table><tr><th>variant</th><th class="num">iterations</th><th class="num">PSNR (dB)</th>'
               '<th class="num">SSIM</th><th>s to 20 / 25 / 30 dB</th><th class="num">render s/image</th>'
               '<th class="num">peak MB</th><th class="num">model MB</th></tr>')
    for v in bench["variants"]:
        reach = " / ".join(_fmt(v["time_to_psnr_s"].get(t), ".0f") for t in ("20", "25", "30"))
        out.append(f"<tr><td>{html.escape(v['name'])}</td><td class=num>{v['final']['iterations']}</td>"
                   f"<td class=num>{v['final']['psnr']:.2f}</td><td class=num>{v['final']['ssim']:.4f}</td>"
                   f"<td>{reach}</td><td class=num>{v['render_seconds_per_image']:.2f}</td>"
                   f"<td class=num>{v['peak_memory_mb']:.0f}</td><td class=num>{v['model_size_mb']:.1f}</td></tr>")
    out.append("</table>")
    budget = bench["budget"]
    out.append(f'<p class="muted">Same dataset, seed {bench["seed"]}, budget {budget.get("seconds", budget.get("iterations"))} '
               f'{"training seconds" if "seconds" in budget else "iterations"} per variant ({html.escape(str(bench_json))}).</p>')
    return "\n".join(out)


def _comparison(page: _Page, results: list[Result], split) -> str:
    out = ["<h2>Runs compared</h2>", '<table><tr><th>result</th><th>preset</th><th class="num">iterations</th>'
           '<th class="num">training s</th><th class="num">PSNR (dB)</th><th class="num">SSIM</th>'
           f'<th class="num">LPIPS</th><th class="num" title="{DEPTH_UNIT_NOTE}">depth MAE ({DEPTH_UNIT})</th></tr>']
    for result in results:
        done = [e for e in result.events if e.get("event") in ("done", "checkpoint")]
        last = done[-1] if done else {}
        preset = result.run_config["preset"] if result.run_config else "other tool"
        m = result.metrics
        out.append(f"<tr><td>{html.escape(result.label)}</td><td>{html.escape(preset)}</td>"
                   f"<td class=num>{last.get('iteration', '—')}</td><td class=num>{_fmt(last.get('elapsed_s'), '.1f')}</td>"
                   f"<td class=num>{m['psnr']:.2f}</td><td class=num>{m['ssim']:.4f}</td>"
                   f"<td class=num>{_fmt(m.get('lpips'), '.4f')}</td><td class=num>{_fmt(m.get('depth_mae'), '.4f')}</td></tr>")
    out.append("</table>")
    first = sorted(results[0].metrics["per_view"], key=lambda v: v["psnr"])
    chosen = [v["view"] for v in first[:COMPARED_VIEWS]]
    stems = [p.stem for p in split.image_paths]
    out.append(f"<h3>The same views from each (the {len(chosen)} worst for {html.escape(results[0].label)})</h3><table>")
    for stem in chosen:
        gt = page.image(f"gt_{stem}.png", pixels=split.rgb_on_white(stems.index(stem)).numpy())
        cells = [f"<td>{page.figure(gt, f'{stem}: Cycles')}</td>"]
        for k, result in enumerate(results):
            render = page.image(f"r{k}_{stem}.png", source=result.renders_dir / f"{stem}.png")
            caption = f"{result.label}: {result.by_view[stem]['psnr']:.2f} dB"
            cells.append(f"<td>{page.figure(render, caption)}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


MARKER = "<!-- written by python -m nerf_backend report -->"


def _clear_previous_report(out_dir: Path) -> None:
    """A report is derived output and is rebuilt whole; a folder holding anything else is
    refused rather than emptied."""
    if not out_dir.exists() or not any(out_dir.iterdir()):
        return
    index = out_dir / "index.html"
    ours = index.is_file() and MARKER in index.read_text(encoding="utf-8", errors="replace")
    if not ours or set(p.name for p in out_dir.iterdir()) - {"index.html", "images"}:
        raise NerfError(f"{out_dir}: folder exists and is not a report written by this tool; choose another --out")
    shutil.rmtree(out_dir)


def write_report(paths: list[Path], out_dir: Path | None = None, split: str = "test") -> Path:
    """Evaluate what needs it and write the page; returns the path of ``index.html``."""
    if not paths:
        raise NerfError("report: give at least one run folder or scored renders folder")
    results = [load_result(Path(p), split) for p in paths]
    datasets = {r.dataset.resolve() for r in results}
    if len(datasets) > 1:
        raise NerfError("report: the results are on different datasets: " + ", ".join(sorted(map(str, datasets))))
    labels = [r.label for r in results]
    for k, result in enumerate(results):  # two folders with one name (run/, run/) stay apart
        if labels.count(result.label) > 1:
            result.label = f"{result.label} ({k + 1})"
    out_dir = Path(out_dir) if out_dir is not None else results[0].path / "report"
    _clear_previous_report(out_dir)
    (out_dir / "images").mkdir(parents=True)
    dataset_split = load_split(results[0].dataset, split)
    page = _Page(out_dir)
    title = "NeRF vs Cycles: " + ", ".join(r.label for r in results)
    page.add(f"<h1>{html.escape(title)}</h1>")
    page.add(f'<p class="muted">Dataset {html.escape(str(results[0].dataset))}, {split} split.</p>')
    if len(results) > 1:
        page.add(_comparison(page, results, dataset_split))
    scale = page.image("error_scale.png")
    _plot_error_scale(out_dir / scale)
    for k, result in enumerate(results):
        page.add(f"<h2>{html.escape(result.label)}</h2>" + _headline(result))
        curves = out_dir / "images" / f"r{k}_training.png"
        if _plot_training(result.events, curves):
            page.add("<h3>Training</h3>" + page.figure(f"images/{curves.name}", "loss and PSNR against iterations and time",
                                                     kind="wide"))
        page.add(f"<h3>Every {split} view, worst first</h3>"
                 f'<p class="muted">Click a column heading to sort; click a picture for full size. Error heatmap scale:</p>'
                 f'<img src="{scale}" alt="error scale">')
        page.add(_views_table(page, result, f"r{k}", dataset_split))
        bench = _find_bench(result.path) if result.run_config is not None else None
        if bench is not None:
            page.add(_bench_section(page, bench))
    return page.write(title)
