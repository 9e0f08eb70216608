"""``python -m nerf_backend report``: a self-contained HTML page comparing NeRF renders with
Cycles ground truth.

``report RUN`` writes ``RUN/report/index.html`` with its images beside it (no network, no
external scripts or styles): the headline metrics and what the run cost, the scene
decisions ``auto`` made, every test view (ground truth, render, error heatmap, metrics;
sortable, worst first; click a picture for full size), the training curves, the geometry
scores when ``eval --geometry`` measured the run, its camera animations, its baked asset as
Blender renders it (``export``, ``datasets_gen --render-asset``, ``eval --renders``) beside the
NeRF, and the bench results when the run sits
inside a bench folder. ``report A B ...`` compares several
results on the same dataset: metrics side by side and the same views from each. A result
is a run folder, or a folder of another tool's renders scored by
``eval --dataset D --renders DIR`` (its ``metrics.json`` says which dataset).
"""

from __future__ import annotations

import html
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

from nerf_contract.run_layout import (
    ANIMATION_RECORD,
    ANIMATIONS_DIR,
    ASSET_COMPLETE,
    ASSET_DIR,
    ASSET_ENGINES,
    ASSET_NAME,
    ASSET_RECORD_SUFFIX,
    ASSET_RENDER_RECORD,
    ASSET_RENDERS_DIR,
    CONFIG_NAME,
    METRICS_NAME,
    REPORT_DIR,
    REPORT_INDEX,
)
from nerf_contract.training_events import Checkpoint, Collapse, Done, Event

from ..core.devices import resolve_device
from ..core.errors import NerfError
from ..data.dataset import load_split
from ..data.run_folder import RunFolder
from ..metrics.registry import METRICS, Metric
from .animation import FRAME_METRICS
from .error_images import error_heatmap
from .evaluate import evaluate_run, read_rgb
from .geometry_eval import GEOMETRY_NAME, GEOMETRY_PICTURE, GEOMETRY_SCORES
from .inference import renders_are_current
from .report_page import MARKER, ReportPage
from .report_plots import plot_error_scale, plot_training

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
    events: list[Event]

    @property
    def by_view(self) -> dict[str, dict]:
        return {v["view"]: v for v in self.metrics["per_view"]}


def load_result(path: Path, split: str) -> Result:
    """A run folder (evaluated now if its metrics are missing or stale) or a folder with
    ``metrics.json`` written by ``eval --dataset D --renders DIR``."""
    path = Path(path)
    if (path / CONFIG_NAME).is_file():
        run = RunFolder(path)
        metrics_path = path / METRICS_NAME
        metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else None
        if metrics is None or metrics.get("split") != split or not renders_are_current(run, split) or "renders" not in metrics:
            metrics = evaluate_run(path, split, resolve_device("auto"), progress=False)
        return Result(_label(path), path, metrics, Path(metrics["renders"]), Path(metrics["dataset"]),
                      run.read_config(), run.read_events())
    metrics_path = path / METRICS_NAME
    if not metrics_path.is_file():
        raise NerfError(f"{path}: neither a run folder (no {CONFIG_NAME}) nor scored renders (no {METRICS_NAME}); "
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


def _metric_header(metric: Metric) -> str:
    return f"{metric.label} ({metric.unit})" if metric.unit else metric.label


def _metric_cells(values: dict) -> str:
    """One table cell per metric of the registry (``—`` where a value is missing)."""
    return "".join(f"<td class=num>{_fmt(values.get(m.key), f'.{m.decimals}f')}</td>" for m in METRICS)


def _metric_headers() -> str:
    return "".join(f'<th class="num">{html.escape(_metric_header(m))}</th>' for m in METRICS)


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


def _find_bench(path: Path) -> Path | None:
    """``bench.json`` in the run folder or the bench folder holding it (BENCH/runs/NAME)."""
    for folder in (path, path.parent, path.parent.parent):
        if (folder / "bench.json").is_file():
            return folder / "bench.json"
    return None


DEPTH_UNIT = "dataset units"
DEPTH_UNIT_NOTE = "mean absolute error of the distance along each ray, in the dataset's frame (after world_to_nerf)"

def _headline(result: Result) -> str:
    m = result.metrics
    cards = [(metric.label, metric.format(m.get(metric.key))) for metric in METRICS]
    if m.get("depth_mae") is not None:
        cards.append(("depth MAE", f"{m['depth_mae']:.4f} {DEPTH_UNIT}"))
    config, events = result.run_config, result.events
    if config is not None:
        last = _last_progress(events)
        cards += [("preset", config["preset"]), ("iterations", str(last.iteration if last else "—")),
                  ("training time", _fmt(last.elapsed_s if last else None, ".1f") + " s"),
                  ("device", config.get("device", "—"))]
    out = ['<div class="headline">'] + [f'<div class="card">{html.escape(k)}<b>{html.escape(v)}</b></div>' for k, v in cards]
    out.append("</div>")
    out += _collapse_alerts(events)
    notes = [f"{m['views']} {m['split']} views. Background: {m['background']}."]
    for metric in METRICS:
        if m.get(metric.key) is None:
            notes.append(f"{metric.label} unavailable: {m.get(f'{metric.key}_unavailable')}.")
    if m.get("lpips") is not None:
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


def _last_progress(events: list[Event]) -> Done | Checkpoint | None:
    """Where training stands: its last ``done`` or ``checkpoint`` event."""
    done = [e for e in events if isinstance(e, (Done, Checkpoint))]
    return done[-1] if done else None


def _collapse_alerts(events: list[Event]) -> list[str]:
    """What the collapse guard found during training and what the trainer did about it."""
    alerts = []
    for event in (e for e in events if isinstance(e, Collapse)):
        verdict = "The run failed: " if event.final else "The run collapsed and was restarted: "
        alerts.append(f'<div class="alert"><b>{html.escape(verdict)}</b>'
                      f'{html.escape(event.reason)}. What the trainer did: {html.escape(event.action)}.</div>')
    return alerts


def _views_table(page: ReportPage, result: Result, prefix: str, split) -> str:
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
        keys = [metric.key for metric in METRICS] + ["depth_mae"]
        data = " ".join(f'data-{k}="{_fmt(view.get(k), ".6f", "nan")}"' for k in keys)
        rows.append(
            f'<tr {data} data-name="{index}"><td>{html.escape(view["view"])}</td><td>{page.figure(gt, "Cycles")}</td>'
            f"<td>{page.figure(render, 'NeRF')}</td><td>{page.figure(error, 'error')}</td>"
            f"{_metric_cells(view)}<td class=num>{_fmt(view.get('depth_mae'), '.4f')}</td></tr>")
    # Worst first: ascending for a metric where higher is better.
    first_order = ' data-order="asc"'
    metric_headers = "".join(
        f'<th class="sortable num" data-key="{m.key}"{first_order if m is METRICS[0] else ""}>'
        f"{html.escape(_metric_header(m))}</th>" for m in METRICS)
    header = ('<table class="views"><thead><tr><th class="sortable" data-key="name">view</th><th>Cycles (ground truth)</th>'
              f"<th>NeRF</th><th>error</th>{metric_headers}"
              f'<th class="sortable num" data-key="depth_mae" title="{DEPTH_UNIT_NOTE}">depth MAE ({DEPTH_UNIT})</th>'
              "</tr></thead><tbody>")
    return header + "\n".join(rows) + "</tbody></table>"


def _bench_section(page: ReportPage, bench_json: Path) -> str:
    bench = json.loads(bench_json.read_text())
    out = ["<h2>Speed and accuracy of the presets (bench)</h2>"]
    if (bench_json.parent / "bench.png").is_file():
        out.append(page.figure(page.image("bench.png", source=bench_json.parent / "bench.png"),
                               "PSNR against training time", kind="wide"))
    out.append(f'<table><tr><th>variant</th><th class="num">iterations</th>{_metric_headers()}'
               '<th>s to 20 / 25 / 30 dB</th><th class="num">render s/image</th>'
               '<th class="num">peak MB</th><th class="num">model MB</th></tr>')
    for v in bench["variants"]:
        reach = " / ".join(_fmt(v["time_to_psnr_s"].get(t), ".0f") for t in ("20", "25", "30"))
        out.append(f"<tr><td>{html.escape(v['name'])}</td><td class=num>{v['final']['iterations']}</td>"
                   f"{_metric_cells(v['final'])}<td>{reach}</td><td class=num>{v['render_seconds_per_image']:.2f}</td>"
                   f"<td class=num>{v['peak_memory_mb']:.0f}</td><td class=num>{v['model_size_mb']:.1f}</td></tr>")
    out.append("</table>")
    budget = bench["budget"]
    out.append(f'<p class="muted">Same dataset, seed {bench["seed"]}, budget {budget.get("seconds", budget.get("iterations"))} '
               f'{"training seconds" if "seconds" in budget else "iterations"} per variant ({html.escape(str(bench_json))}).</p>')
    return "\n".join(out)


def _geometry_section(page: ReportPage, run: Path, prefix: str) -> str:
    """The run's surface against the scene's true one, as ``eval --geometry`` measured it."""
    geometry = json.loads((run / GEOMETRY_NAME).read_text())
    mesh, truth = geometry["mesh"], geometry["truth"]
    out = ["<h3>Geometry against the scene's true surface</h3>",
           '<table><tr><th>score</th><th class="num">value</th></tr>']
    out += [f"<tr><td>{html.escape(label)}</td><td class=num>{_fmt(geometry.get(key), f'.{decimals}f')}</td></tr>"
            for key, label, decimals in GEOMETRY_SCORES]
    out.append("</table>")
    if (run / GEOMETRY_PICTURE).is_file():
        picture = page.image(f"{prefix}_geometry.png", source=run / GEOMETRY_PICTURE)
        out.append(page.figure(picture, "the NeRF's surface coloured by its distance to the truth (grey)", kind="wide"))
    notes = [f"τ = {geometry['tau']:.4g} {geometry['units']}: {geometry['tau_rule']}.",
             f"The mesh of iteration {mesh['iteration']} at resolution {mesh['resolution']}, density "
             f"{mesh['threshold']:.4g} ({mesh['threshold_rule']}); {geometry['samples']['nerf']:,} points on the NeRF's "
             f"surface and {geometry['samples']['truth']:,} on the truth, {geometry['sampling']}.",
             f"Truth: {truth['file']} ({truth['triangles']} triangles)."]
    notes += [f"Left out of the truth: {entry}." for entry in truth["left_out"]]
    out.append("".join(f'<p class="muted">{html.escape(n)}</p>' for n in notes))
    return "\n".join(out)


def _animation_sections(page: ReportPage, run: Path, prefix: str) -> str:
    """Each camera animation rendered with the run (``render --camera-path``): its video (side
    by side with Cycles when compared), the per-frame scores and their plot."""
    out = []
    for record_path in sorted((run / ANIMATIONS_DIR).glob(f"*/{ANIMATION_RECORD}")):
        record = json.loads(record_path.read_text())
        if record.get("video") is None:
            continue  # not finished
        folder, name = record_path.parent, record_path.parent.name
        compared = record.get("side_by_side_video") is not None
        video = page.image(f"{prefix}_{name}.mp4", source=folder / ("side_by_side.mp4" if compared else "nerf.mp4"))
        width, height = record["size"]
        speed = _fmt(record.get("seconds_per_frame"), ".2f")
        out.append(f"<h3>Animation: {html.escape(record['camera'])}</h3>"
                   f'<video controls loop muted preload="metadata" src="{video}" class="wide"></video>'
                   f'<p class="muted">{len(record["frames"])} frames (Blender frames {record["frames"][0]}–'
                   f'{record["frames"][-1]}) at {width}×{height}, {record["fps"]:g} fps; {speed} s a frame on '
                   f'{html.escape(record["device"])} at iteration {record["iteration"]}.'
                   + (" Left to right: Cycles, NeRF, error." if compared else "") + "</p>")
        if compared:
            metrics = json.loads((folder / "frame_metrics.json").read_text())
            out.append('<table><tr><th>against Cycles</th>' + "".join(
                f'<th class="num">{html.escape(_metric_header(m))}</th>' for m in FRAME_METRICS) + "</tr>")
            worst = min(metrics["frames"], key=lambda f: f["psnr"])
            for label, values in (("mean of the frames", metrics["mean"]), (f"worst frame ({worst['frame']})", worst)):
                out.append(f"<tr><td>{label}</td>" + "".join(
                    f"<td class=num>{html.escape(m.format(values.get(m.key)))}</td>" for m in FRAME_METRICS) + "</tr>")
            out.append("</table>")
            plot = page.image(f"{prefix}_{name}_metrics.png", source=folder / "frame_metrics.png")
            out.append(page.figure(plot, "PSNR and SSIM of each frame against Cycles", kind="wide"))
    return "\n".join(out)


ASSET_VIEWS = 3


def _asset_section(page: ReportPage, result: Result, prefix: str, split) -> str:
    """The run's baked asset (``export``), rendered by Blender from the test cameras (``datasets_gen
    --render-asset``) and scored (``eval --renders``): the trade table against the NeRF itself, and
    Cycles, the NeRF and the asset side by side on the asset's worst views."""
    folder = result.path / ASSET_DIR
    try:
        record = json.loads((folder / (ASSET_NAME + ASSET_RECORD_SUFFIX)).read_text())
    except (OSError, ValueError):
        return ""
    if not record.get(ASSET_COMPLETE):
        return ""
    scored = {}
    for engine in ASSET_ENGINES:
        renders = folder / ASSET_RENDERS_DIR / engine
        try:
            scored[engine] = (renders, json.loads((renders / METRICS_NAME).read_text()),
                              json.loads((renders / ASSET_RENDER_RECORD).read_text()))
        except (OSError, ValueError):
            continue
    size = f"{record['texture_size']}²"
    out = ["<h3>The baked asset in Blender's renders</h3>",
           '<table><tr><th>rendered by</th><th class="num">triangles</th><th class="num">texture</th>'
           f'<th class="num">file MB</th>{_metric_headers()}<th class="num">s a view</th></tr>',
           f"<tr><td>the NeRF itself (volume rendering)</td><td class=num>—</td><td class=num>—</td>"
           f"<td class=num>—</td>{_metric_cells(result.metrics)}<td class=num>—</td></tr>"]
    for engine, (_, metrics, render) in scored.items():
        out.append(f"<tr><td>the asset, {html.escape(render['render_engine'])} (Blender {html.escape(render['blender_version'])})"
                   f"</td><td class=num>{record['triangles']:,}</td><td class=num>{size}</td>"
                   f"<td class=num>{record['bytes'] / 1e6:.2f}</td>{_metric_cells(metrics)}"
                   f"<td class=num>{render['seconds'] / max(1, render['views']):.2f}</td></tr>")
    out.append("</table>")
    notes = [f"{ASSET_NAME}: {record['triangles']:,} triangles of the surface's {record['surface_triangles']:,} "
             f"(budget {record['triangle_budget']:,}), a {size} texture ({record['texels_covered']:.0%} of its texels "
             f"covered); {record['bake']}.",
             "Viewport frame rate: not measured in a headless session."]
    if not scored:
        notes.append("Not rendered yet: python -m datasets_gen --render-asset ASSET.glb --dataset DATASET "
                     "--out RUN/asset/renders/cycles, then python -m nerf_backend eval --dataset DATASET --renders "
                     "that folder.")
    out.append("".join(f'<p class="muted">{html.escape(n)}</p>' for n in notes))
    if scored:
        first_engine, (first_renders, first_metrics, _) = next(iter(scored.items()))
        worst = sorted(first_metrics["per_view"], key=lambda v: v["psnr"])[:ASSET_VIEWS]
        stems = [p.stem for p in split.image_paths]
        out.append("<table><tr><th>Cycles (ground truth)</th><th>NeRF</th>"
                   + "".join(f"<th>asset, {engine}</th>" for engine in scored) + "</tr>")
        for view in worst:
            stem = view["view"]
            cells = [page.figure(page.image(f"gt_{stem}.png", pixels=split.rgb_on_white(stems.index(stem)).numpy()),
                                 f"{stem}: Cycles"),
                     page.figure(page.image(f"{prefix}_{stem}.png", source=result.renders_dir / f"{stem}.png"),
                                 f"NeRF: {result.by_view[stem]['psnr']:.2f} dB")]
            for engine, (renders, metrics, _) in scored.items():
                psnr = next(v["psnr"] for v in metrics["per_view"] if v["view"] == stem)
                cells.append(page.figure(page.image(f"{prefix}_asset_{engine}_{stem}.png",
                                                    pixels=read_rgb(renders / f"{stem}.png")),
                                         f"asset, {engine}: {psnr:.2f} dB"))
            out.append("<tr>" + "".join(f"<td>{cell}</td>" for cell in cells) + "</tr>")
        out.append("</table>")
    return "\n".join(out)


def _comparison(page: ReportPage, results: list[Result], split) -> str:
    out = ["<h2>Runs compared</h2>", '<table><tr><th>result</th><th>preset</th><th class="num">iterations</th>'
           f'<th class="num">training s</th>{_metric_headers()}'
           f'<th class="num" title="{DEPTH_UNIT_NOTE}">depth MAE ({DEPTH_UNIT})</th></tr>']
    for result in results:
        last = _last_progress(result.events)
        preset = result.run_config["preset"] if result.run_config else "other tool"
        m = result.metrics
        out.append(f"<tr><td>{html.escape(result.label)}</td><td>{html.escape(preset)}</td>"
                   f"<td class=num>{last.iteration if last else '—'}</td>"
                   f"<td class=num>{_fmt(last.elapsed_s if last else None, '.1f')}</td>"
                   f"{_metric_cells(m)}<td class=num>{_fmt(m.get('depth_mae'), '.4f')}</td></tr>")
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


def _clear_previous_report(out_dir: Path) -> None:
    """A report is derived output and is rebuilt whole; a folder holding anything else is
    refused rather than emptied."""
    if not out_dir.exists() or not any(out_dir.iterdir()):
        return
    index = out_dir / REPORT_INDEX
    ours = index.is_file() and MARKER in index.read_text(encoding="utf-8", errors="replace")
    if not ours or set(p.name for p in out_dir.iterdir()) - {REPORT_INDEX, "images"}:
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
    out_dir = Path(out_dir) if out_dir is not None else results[0].path / REPORT_DIR
    _clear_previous_report(out_dir)
    (out_dir / "images").mkdir(parents=True)
    dataset_split = load_split(results[0].dataset, split)
    page = ReportPage(out_dir)
    title = "NeRF vs Cycles: " + ", ".join(r.label for r in results)
    page.add(f"<h1>{html.escape(title)}</h1>")
    page.add(f'<p class="muted">Dataset {html.escape(str(results[0].dataset))}, {split} split.</p>')
    if len(results) > 1:
        page.add(_comparison(page, results, dataset_split))
    scale = page.image("error_scale.png")
    plot_error_scale(out_dir / scale)
    for k, result in enumerate(results):
        page.add(f"<h2>{html.escape(result.label)}</h2>" + _headline(result))
        curves = out_dir / "images" / f"r{k}_training.png"
        if plot_training(result.events, curves):
            page.add("<h3>Training</h3>" + page.figure(f"images/{curves.name}", "loss and PSNR against iterations and time",
                                                     kind="wide"))
        page.add(f"<h3>Every {split} view, worst first</h3>"
                 f'<p class="muted">Click a column heading to sort; click a picture for full size. Error heatmap scale:</p>'
                 f'<img src="{scale}" alt="error scale">')
        page.add(_views_table(page, result, f"r{k}", dataset_split))
        if result.run_config is not None and (result.path / GEOMETRY_NAME).is_file():
            page.add(_geometry_section(page, result.path, f"r{k}"))
        if result.run_config is not None:
            page.add(_animation_sections(page, result.path, f"r{k}"))
            page.add(_asset_section(page, result, f"r{k}", dataset_split))
        bench = _find_bench(result.path) if result.run_config is not None else None
        if bench is not None:
            page.add(_bench_section(page, bench))
    return page.write(title)
