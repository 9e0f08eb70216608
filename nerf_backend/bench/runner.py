"""Training and measuring each variant of one dataset, each in its own process: ``run_bench``
writes ``bench.json``, ``bench.md`` and ``bench.png``."""

from __future__ import annotations

import io
import multiprocessing
import queue as queue_module
import resource
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch

from ..core.devices import machine_record, resolve_device
from ..core.errors import NerfError
from ..core.files import write_json
from ..core.provenance import provenance
from ..data.dataset import load_split
from ..data.run_folder import RunFolder
from ..evaluation.geometry_eval import TAU_RULE, scene_tau, score_geometry, truth_file
from ..evaluation.inference import load_trained_model
from ..evaluation.render_views import render_image
from ..metrics.registry import MetricTools, mean_scores, score_image
from ..training.trainer import TrainOptions, train
from .curves import THRESHOLDS_DB, curve_points, time_to_reach
from .tables import markdown_table, plot_curves
from .variants import Variant, ablation_order

# The bench scores without LPIPS: its weights are optional, and a bench must run anywhere.
BENCH_TOOLS = MetricTools(lpips_unavailable="the bench does not load LPIPS weights")
# Marching cubes at a modest resolution: a few seconds a variant on a CPU.
BENCH_MESH_RESOLUTION = 128


def _score(run_dir: Path, split, indices: list[int], device: torch.device) -> tuple[dict, float]:
    """Each metric's mean over ``indices`` of ``split`` (the same scoring as ``eval``, on the
    image as it would be written to PNG) and the render seconds per image."""
    model, ray_bounds, _ = load_trained_model(RunFolder(run_dir), device)
    per_view, seconds = [], []
    for index in indices:
        start = time.perf_counter()
        image = render_image(model, split.intrinsics, split.poses[index], ray_bounds)
        seconds.append(time.perf_counter() - start)
        rendered = np.round(image.rgb * 255) / 255  # as written to PNG
        per_view.append(score_image(rendered, split.rgb_on_white(index).numpy(), BENCH_TOOLS))
    return mean_scores(per_view), float(np.mean(seconds))


def _geometry(run_dir: Path, dataset: str, device: torch.device) -> dict:
    """The final checkpoint's Chamfer distance and F-score against the scene's true surface
    (``eval --geometry`` at BENCH_MESH_RESOLUTION); nothing for a dataset without one, None
    and the reason when there is no mesh to measure (a collapsed variant has no surface)."""
    if truth_file(dataset) is None:
        return {}
    try:
        record = score_geometry(RunFolder(run_dir), device, BENCH_MESH_RESOLUTION)
    except NerfError as exc:
        return {"chamfer": None, "f_score": None, "geometry_unavailable": str(exc)}
    return {"chamfer": record["chamfer"], "f_score": record["f_score"]}


def _geometry_record(dataset: Path) -> dict | None:
    """How the variants' geometry was measured, or None for a dataset without a true surface."""
    truth = truth_file(dataset)
    if truth is None:
        return None
    return {"truth": str(truth), "mesh_resolution": BENCH_MESH_RESOLUTION, "tau": scene_tau(dataset),
            "tau_rule": TAU_RULE}


def bench_variant(dataset: str, variant: Variant, out_dir: str, budget_seconds: float | None,
                  iterations: int | None, points: int | tuple[float, ...], curve_views: int, seed: int,
                  device_name: str) -> dict:
    """Train and measure one variant (runs in a child process)."""
    device = resolve_device(device_name)
    test = load_split(dataset, "test")
    curve_indices = sorted({round(i) for i in np.linspace(0, len(test) - 1, min(curve_views, len(test)))})
    run_dir = Path(out_dir) / "runs" / variant.name
    curve = []
    summary = None
    for k, target in enumerate(curve_points(budget_seconds, iterations, points)):
        summary = train(TrainOptions(
            dataset=Path(dataset), run=run_dir, preset=variant.preset if k == 0 else None,
            overrides=variant.overrides if k == 0 else (), seed=seed, device=device_name,
            # Scored at points along one run: the schedule spans the whole budget.
            max_seconds=target if budget_seconds is not None else None, schedule_seconds=budget_seconds,
            iterations=int(target) if iterations is not None else None,
            resume=k > 0, overwrite=k == 0, progress=False,
        ))
        scores, _ = _score(run_dir, test, curve_indices, device)
        curve.append({"train_seconds": summary.train_seconds, "iteration": summary.iteration, **scores})
        print(f"bench {variant.name}: {summary.iteration} it, {summary.train_seconds:.1f} s, "
              f"PSNR {scores['psnr']:.2f} dB on {len(curve_indices)} test views", file=sys.stderr, flush=True)
    final_scores, render_seconds = _score(run_dir, test, list(range(len(test))), device)
    geometry = _geometry(run_dir, dataset, device)
    model, _, _ = load_trained_model(RunFolder(run_dir), device)
    buffer = io.BytesIO()
    torch.save(model.state_dict(), buffer)
    return {
        "name": variant.name, "preset": variant.preset, "overrides": list(variant.overrides),
        "curve": curve,
        "time_to_psnr_s": {f"{t:g}": time_to_reach(curve, t) for t in THRESHOLDS_DB},
        "final": {**final_scores, **geometry, "test_views": len(test),
                  "iterations": summary.iteration, "train_seconds": summary.train_seconds,
                  "rays_per_second": summary.rays_per_second, "samples_per_second": summary.samples_per_second},
        "render_seconds_per_image": render_seconds,
        "peak_memory_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "model_size_mb": buffer.getbuffer().nbytes / 2**20,
        "image_size": [test.intrinsics.width, test.intrinsics.height],
    }


def _child(queue, *args) -> None:
    try:
        queue.put(("ok", bench_variant(*args)))
    except BaseException as exc:  # reported by the parent with the variant's name
        queue.put(("error", f"{type(exc).__name__}: {exc}"))


def _result(queue, process) -> tuple[str, object]:
    """The variant's result, or an error once its process has died without one (killed by
    the system, say) instead of waiting for ever."""
    while True:
        try:
            return queue.get(timeout=1.0)
        except queue_module.Empty:
            if not process.is_alive():
                return "error", f"its process ended (exit code {process.exitcode}) without a result"


def _raise_exit(signum, frame) -> None:
    raise SystemExit(128 + signum)


def variant_processes() -> multiprocessing.context.BaseContext:
    """How each variant's process starts. Still a process of its own, which never ran another
    variant; on Linux forked from a server that imported torch and the backend once (importing
    them took 3 s a variant here), elsewhere spawned (Windows has no fork, and macOS's system
    frameworks are not safe to fork once loaded)."""
    if not sys.platform.startswith("linux"):
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([__name__])
    return context


def run_bench(dataset: Path, variants: list[Variant], out_dir: Path, budget_seconds: float | None,
              iterations: int | None, points: int | tuple[float, ...] = 6, curve_views: int = 8, seed: int = 0,
              device: str = "auto", overwrite: bool = False, command: str | None = None) -> dict:
    """Bench ``variants`` on ``dataset`` into ``out_dir``; ``command`` is the command line that
    asked for it, recorded with the source's commit in the tables."""
    if (budget_seconds is None) == (iterations is None):
        raise NerfError("bench: give exactly one of --budget-seconds or --iters")
    try:
        curve_points(budget_seconds, iterations, points)
    except ValueError as exc:
        raise NerfError(f"bench --points: {exc}") from None
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise NerfError(f"{out_dir}: bench folder exists and is not empty; pass --overwrite to replace it")
    out_dir.mkdir(parents=True, exist_ok=True)
    context = variant_processes()
    results = []
    # SIGTERM becomes an exception here, so that the variant's process is stopped with us
    # (an orphan would go on training and hold its run folder's lock).
    previous = signal.signal(signal.SIGTERM, _raise_exit) if threading.current_thread() is threading.main_thread() else None
    try:
        for variant in variants:
            queue = context.Queue()
            process = context.Process(target=_child, args=(queue, str(dataset), variant, str(out_dir), budget_seconds,
                                                           iterations, points, curve_views, seed, device))
            process.start()
            try:
                status, payload = _result(queue, process)
                process.join()
            finally:
                if process.is_alive():  # we are being stopped: so is the variant (SIGTERM would only end its segment)
                    process.kill()
                    process.join()
            if status != "ok":
                raise NerfError(f"bench: variant {variant.name!r} failed: {payload}")
            results.append(payload)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    report = {
        "dataset": str(dataset.resolve()), "seed": seed, "device": device,
        "budget": {"seconds": budget_seconds} if budget_seconds is not None else {"iterations": iterations},
        "machine": machine_record(resolve_device(device)),
        "provenance": provenance(command),
        "variants": results,
        "ablation_order": ablation_order(results),
        "geometry": _geometry_record(dataset),
    }
    write_json(out_dir / "bench.json", report)
    (out_dir / "bench.md").write_text(markdown_table(report))
    plot_curves(report, out_dir / "bench.png")
    return report
