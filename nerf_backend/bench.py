"""``python -m nerf_backend bench``: the speed/accuracy trade of several presets, measured
on the same dataset, seed and budget in one run.

Each preset trains in its own child process (so its peak memory is its own) in segments:
train up to the next point in time (or iteration), score a fixed subset of test views,
resume. Scoring time is not training time. At the end every test view is rendered and
scored, and render seconds per image, peak memory and model size are recorded. Results:
``bench.json``, ``bench.md`` (a table) and ``bench.png`` (PSNR against training time).

A variant is a preset with changes: ``NAME=PRESET+KEY=VALUE+...`` (``--set`` syntax), e.g.
``no_pe=paper+field.position_frequencies=0+field.direction_frequencies=0``.
"""

from __future__ import annotations

import io
import json
import math
import multiprocessing
import queue as queue_module
import resource
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .errors import NerfError
from .files import write_json

THRESHOLDS_DB = (20.0, 25.0, 30.0)
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


def _checkpoints(budget_seconds: float | None, iterations: int | None, points: int) -> list[float]:
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


def _score(run_dir: Path, split, indices: list[int], device: torch.device) -> tuple[float, float, float]:
    """Mean PSNR, SSIM and render seconds per image over ``indices`` of ``split``."""
    from .inference import load_trained_model
    from .metrics import psnr, ssim
    from .render_views import render_image
    from .run_folder import RunFolder

    model, ray_bounds, _ = load_trained_model(RunFolder(run_dir), device)
    psnrs, ssims, seconds = [], [], []
    for index in indices:
        start = time.perf_counter()
        image = render_image(model, split.intrinsics, split.poses[index], ray_bounds)
        seconds.append(time.perf_counter() - start)
        rendered = np.round(image.rgb * 255) / 255  # as written to PNG
        reference = split.rgb_on_white(index).numpy()
        psnrs.append(psnr(rendered, reference))
        ssims.append(ssim(rendered, reference))
    return float(np.mean(psnrs)), float(np.mean(ssims)), float(np.mean(seconds))


def bench_variant(dataset: str, variant: Variant, out_dir: str, budget_seconds: float | None,
                  iterations: int | None, points: int, curve_views: int, seed: int, device_name: str) -> dict:
    """Train and measure one variant (runs in a child process)."""
    from .dataset import load_split
    from .devices import resolve_device
    from .trainer import TrainOptions, train

    device = resolve_device(device_name)
    test = load_split(dataset, "test")
    curve_indices = sorted({round(i) for i in np.linspace(0, len(test) - 1, min(curve_views, len(test)))})
    run_dir = Path(out_dir) / "runs" / variant.name
    curve = []
    summary = None
    for k, target in enumerate(_checkpoints(budget_seconds, iterations, points)):
        summary = train(TrainOptions(
            dataset=Path(dataset), run=run_dir, preset=variant.preset if k == 0 else None,
            overrides=variant.overrides if k == 0 else (), seed=seed, device=device_name,
            max_seconds=target if budget_seconds is not None else None,
            iterations=int(target) if iterations is not None else (10**9 if k == 0 else None),
            resume=k > 0, overwrite=k == 0, progress=False,
        ))
        value, similarity, _ = _score(run_dir, test, curve_indices, device)
        curve.append({"train_seconds": summary.train_seconds, "iteration": summary.iteration,
                      "psnr": value, "ssim": similarity})
        print(f"bench {variant.name}: {summary.iteration} it, {summary.train_seconds:.1f} s, "
              f"PSNR {value:.2f} dB on {len(curve_indices)} test views", file=sys.stderr, flush=True)
    final_psnr, final_ssim, render_seconds = _score(run_dir, test, list(range(len(test))), device)
    from .inference import load_trained_model
    from .run_folder import RunFolder

    model, _, _ = load_trained_model(RunFolder(run_dir), device)
    buffer = io.BytesIO()
    torch.save(model.state_dict(), buffer)
    return {
        "name": variant.name, "preset": variant.preset, "overrides": list(variant.overrides),
        "curve": curve,
        "time_to_psnr_s": {f"{t:g}": time_to_reach(curve, t) for t in THRESHOLDS_DB},
        "final": {"psnr": final_psnr, "ssim": final_ssim, "test_views": len(test),
                  "iterations": summary.iteration, "train_seconds": summary.train_seconds},
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


def run_bench(dataset: Path, variants: list[Variant], out_dir: Path, budget_seconds: float | None,
              iterations: int | None, points: int = 6, curve_views: int = 8, seed: int = 0,
              device: str = "auto", overwrite: bool = False) -> dict:
    if (budget_seconds is None) == (iterations is None):
        raise NerfError("bench: give exactly one of --budget-seconds or --iters")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise NerfError(f"{out_dir}: bench folder exists and is not empty; pass --overwrite to replace it")
    out_dir.mkdir(parents=True, exist_ok=True)
    context = multiprocessing.get_context("spawn")
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
        "machine": {"torch": torch.__version__, "threads": torch.get_num_threads()},
        "variants": results,
        "ablation_order": ablation_order(results),
    }
    write_json(out_dir / "bench.json", report)
    (out_dir / "bench.md").write_text(markdown_table(report))
    plot_curves(report, out_dir / "bench.png")
    return report


def step_cost(dataset: Path, preset: str, steps: int, out_dir: Path, seed: int = 0, rays: int | None = None,
              overwrite: bool = False) -> dict:
    """Seconds per training iteration of a NeRF preset through this project's trainer,
    against ``plain_nerf.PlainNerf`` (the same maths written plainly) on the same data,
    rays per batch, threads and seed. Each side takes one untimed warm-up step."""
    from .config import preset_config
    from .dataset import composite, load_split
    from .models import build_model
    from .plain_nerf import PlainNerf, plain_rays
    from .trainer import TrainOptions, train

    config = preset_config(preset)
    if config.model != "nerf" or not config.field.view_dependent:
        raise NerfError(f"bench-step: {preset!r} is not a view-dependent NeRF preset; the plain yardstick is a NeRF MLP")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise NerfError(f"{out_dir}: bench folder exists and is not empty; pass --overwrite to replace it")
    out_dir.mkdir(parents=True, exist_ok=True)
    rays = rays or config.rays_per_batch
    overrides = (f"rays_per_batch={rays}", "checkpoint_every=1000000000")
    run_dir = out_dir / "runs" / preset
    common = dict(dataset=dataset, run=run_dir, seed=seed, progress=False, validate=False)
    warm = train(TrainOptions(**common, preset=preset, overrides=overrides, iterations=1, overwrite=True))
    timed = train(TrainOptions(**common, iterations=1 + steps, resume=True))
    ours = (timed.train_seconds - warm.train_seconds) / steps

    config = preset_config(preset)
    split = load_split(dataset, "train")
    torch.manual_seed(seed)
    plain = PlainNerf(config)
    optimizer = torch.optim.Adam(plain.parameters(), lr=config.learning_rate, betas=config.adam_betas,
                                 eps=config.adam_eps)
    count, height, width = split.rgba.shape[:3]
    intrinsics = split.intrinsics
    seconds = []
    for step in range(1 + steps):
        start = time.perf_counter()
        image = torch.randint(count, (rays,))
        px, py = torch.randint(width, (rays,)), torch.randint(height, (rays,))
        rays_o, rays_d = plain_rays(intrinsics.fl_x, intrinsics.fl_y, intrinsics.cx, intrinsics.cy,
                                    split.poses[image], px.float(), py.float())
        loss = plain.loss(rays_o, rays_d, composite(split.rgba[image, py, px]))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step > 0:
            seconds.append(time.perf_counter() - start)
    plain_seconds = float(np.mean(seconds))
    ours_parameters = sum(p.numel() for p in build_model(config, None).parameters())
    plain_parameters = sum(p.numel() for p in plain.parameters())
    report = {
        "dataset": str(Path(dataset).resolve()), "preset": preset, "rays_per_batch": rays, "steps": steps,
        "seed": seed, "machine": {"torch": torch.__version__, "threads": torch.get_num_threads()},
        "seconds_per_iteration": {"project": ours, "plain": plain_seconds},
        "ratio_project_to_plain": ours / plain_seconds,
        "parameters": {"project": ours_parameters, "plain": plain_parameters},
        "comparison": ("this project's trainer (ray batch, coarse + fine render, loss, backward, Adam) against "
                       "nerf_backend/plain_nerf.py: the same MLPs, encodings, sample counts and optimiser written "
                       "plainly (one MLP call a pass, cumprod compositing, searchsorted resampling)"),
    }
    write_json(out_dir / "step_cost.json", report)
    return report


def _fmt(value: float | None, spec: str) -> str:
    return "—" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def markdown_table(report: dict) -> str:
    budget = report["budget"]
    lines = [
        f"Budget: {budget.get('seconds', budget.get('iterations'))} "
        f"{'training seconds' if 'seconds' in budget else 'iterations'} per variant, seed {report['seed']}, "
        f"torch {report['machine']['torch']} on {report['machine']['threads']} threads.",
        "",
        "| variant | iterations | test PSNR (dB) | SSIM | s to 20 / 25 / 30 dB | render s/image | peak MB | model MB |",
        "| --- | ---: | ---: | ---: | --- | ---: | ---: | ---: |",
    ]
    for v in report["variants"]:
        reach = " / ".join(_fmt(v["time_to_psnr_s"][f"{t:g}"], ".0f") for t in THRESHOLDS_DB)
        lines.append(f"| {v['name']} | {v['final']['iterations']} | {v['final']['psnr']:.2f} | {v['final']['ssim']:.4f} "
                     f"| {reach} | {v['render_seconds_per_image']:.2f} | {v['peak_memory_mb']:.0f} "
                     f"| {v['model_size_mb']:.1f} |")
    if report.get("ablation_order"):
        lines += ["", "Ablations against the NeRF paper's order (its Table 2):", ""]
        for check in report["ablation_order"]:
            lines.append(f"- {check['claim']}: {check['psnr'][0]:.2f} vs {check['psnr'][1]:.2f} dB — "
                         f"{'agrees' if check['holds'] else 'does not agree'} with the paper")
    return "\n".join(lines) + "\n"


def plot_curves(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
