"""``bench --suite``: the same variants, budget and seed on every dataset of a folder, and a
summary across the scenes.

Each dataset is benched as a single ``bench`` would (``run_bench`` into ``BENCH/NAME``: its
bench.json, bench.md and bench.png); ``BENCH/summary.{json,md,png}`` then hold, for each scene
and variant, the final test PSNR and SSIM, the training seconds to 25 and 30 dB, seconds per
training iteration, iterations, the scene's blank-image PSNR and whether the run collapsed;
and for each scene the best fixed variant (any whose preset is not ``auto``) and ``auto``'s
gap to it.

Collapse, two ways: *detected* when the trainer's guard logged a ``collapse`` event in the
variant's ``events.jsonl`` (its validation PSNR stayed near the blank image's, whatever it then
did about it); *collapsed* when the final test PSNR is within ``COLLAPSE_MARGIN_DB`` of the
blank image's on the same test views (or below it).

The blank image is what an empty model renders: all white.  Its PSNR is scored against each
test view composited on white (as every render is scored) and averaged over the views, as the
test PSNR is; a view with nothing in it (the blank image matches it exactly) is left out of
that mean and counted.

The folder resumes scene by scene: ``BENCH/suite.json`` marks it as a suite bench; a scene whose
``bench.json`` was written with this call's variants, budget, seed and dataset is kept, a scene
folder without one (an interrupted bench) is benched again, and a finished bench made with
other settings is refused, before anything runs, unless ``--overwrite``.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nerf_contract.dataset_layout import transforms_name
from nerf_contract.training_events import Collapse

from ..core.devices import machine_record, resolve_device
from ..core.errors import NerfError
from ..core.files import write_json
from ..core.provenance import provenance
from ..data.dataset import load_split
from ..data.run_folder import RunFolder
from ..training.collapse_guard import blank_psnr
from .runner import run_bench
from .tables import plot_suite, suite_markdown
from .variants import Variant

COLLAPSE_MARGIN_DB = 1.0
SUITE_THRESHOLDS_DB = (25.0, 30.0)
PLAN_NAME = "suite.json"
DATASET_MARKER = transforms_name("train")


@dataclass(frozen=True)
class SuiteDataset:
    name: str
    path: Path


def find_datasets(paths: list[Path]) -> tuple[list[SuiteDataset], list[Path]]:
    """The datasets named by ``paths`` (each a dataset, or a folder whose subfolders with a
    ``transforms_train.json`` are datasets), and the subfolders skipped for having none (an
    unfinished render). Two datasets may not share a name (the folder's name)."""
    found: list[SuiteDataset] = []
    skipped: list[Path] = []
    for path in paths:
        if (path / DATASET_MARKER).is_file():
            found.append(SuiteDataset(path.name, path))
        elif path.is_dir():
            folders = sorted(p for p in path.iterdir() if p.is_dir())
            inside = [SuiteDataset(p.name, p) for p in folders if (p / DATASET_MARKER).is_file()]
            if not inside:
                raise NerfError(f"{path}: neither a dataset nor a folder of datasets (no {DATASET_MARKER} in it "
                                "or in its subfolders)")
            found += inside
            skipped += [p for p in folders if not (p / DATASET_MARKER).is_file()]
        else:
            raise NerfError(f"{path}: no such dataset or folder")
    seen: dict[str, Path] = {}
    for dataset in found:
        if dataset.name in seen:
            raise NerfError(f"bench --suite: two datasets are named {dataset.name!r} ({seen[dataset.name]} and "
                            f"{dataset.path}); each scene's results go to BENCH/NAME")
        seen[dataset.name] = dataset.path
    return found, skipped


def scene_blank_psnr(dataset: Path) -> dict:
    """The blank white image's mean PSNR over the test views (composited on white), with the
    number of views it is averaged over and of views left out for having nothing in them."""
    test = load_split(dataset, "test")
    values = [blank_psnr(test.rgb_on_white(index).numpy()) for index in range(len(test))]
    finite = [value for value in values if math.isfinite(value)]
    return {"psnr": float(np.mean(finite)) if finite else None, "views": len(finite),
            "empty_views": len(values) - len(finite)}


def collapse_events(run_dir: Path) -> list[dict]:
    """The trainer's ``collapse`` events in a run's ``events.jsonl`` (all segments of a bench)."""
    keys = ("iteration", "val_psnr", "blank_psnr", "margin_db", "action", "reason")
    return [{key: getattr(event, key) for key in keys} for event in RunFolder(run_dir).read_events()
            if isinstance(event, Collapse)]


def scene_summary(dataset: SuiteDataset, bench: dict, bench_dir: Path) -> dict:
    """One scene's summary: a row per variant, the best fixed variant and auto's gap to it."""
    blank = scene_blank_psnr(dataset.path)
    rows = []
    for variant in bench["variants"]:
        final = variant["final"]
        events = collapse_events(bench_dir / "runs" / variant["name"])
        rows.append({
            "variant": variant["name"], "preset": variant["preset"],
            "psnr": final["psnr"], "ssim": final["ssim"],
            **{f"time_to_{t:g}_db_s": variant["time_to_psnr_s"].get(f"{t:g}") for t in SUITE_THRESHOLDS_DB},
            "seconds_per_iteration": final["train_seconds"] / final["iterations"] if final["iterations"] else None,
            "iterations": final["iterations"],
            "rays_per_second": final.get("rays_per_second"), "samples_per_second": final.get("samples_per_second"),
            "blank_psnr": blank["psnr"],
            "collapse_detected": bool(events),
            "collapse_events": events,
            "collapsed": blank["psnr"] is not None and final["psnr"] < blank["psnr"] + COLLAPSE_MARGIN_DB,
        })
    fixed = [row for row in rows if row["preset"] != "auto"]
    best = max(fixed, key=lambda row: row["psnr"]) if fixed else None
    auto = next((row for row in rows if row["variant"] == "auto"), None) or next(
        (row for row in rows if row["preset"] == "auto"), None)
    return {
        "scene": dataset.name, "dataset": str(dataset.path.resolve()), "bench": str(bench_dir),
        "blank_psnr": blank["psnr"], "blank_views": blank["views"], "empty_test_views": blank["empty_views"],
        "variants": rows,
        "best_fixed": {"variant": best["variant"], "psnr": best["psnr"]} if best else None,
        "auto": ({"variant": auto["variant"], "psnr": auto["psnr"],
                  "gap_to_best_fixed_db": auto["psnr"] - best["psnr"] if best else None} if auto else None),
    }


def _plan(datasets: list[SuiteDataset], variants: list[Variant], budget: dict, points: int | tuple[float, ...],
          curve_views: int, seed: int, device: str) -> dict:
    return {
        "datasets": {dataset.name: str(dataset.path.resolve()) for dataset in datasets},
        "variants": [{"name": v.name, "preset": v.preset, "overrides": list(v.overrides)} for v in variants],
        "budget": budget, "points": list(points) if isinstance(points, tuple) else points,
        "curve_views": curve_views, "seed": seed, "device": device,
    }


def _finished_bench_differences(bench: dict, dataset: SuiteDataset, plan: dict) -> list[str]:
    """What differs between a finished bench.json and this call (empty: it can be kept)."""
    differences = []
    if bench.get("dataset") != str(dataset.path.resolve()):
        differences.append(f"dataset {bench.get('dataset')} there vs {dataset.path.resolve()} now")
    done = [{"name": v["name"], "preset": v["preset"], "overrides": v["overrides"]} for v in bench.get("variants", [])]
    names_there, names_now = [v["name"] for v in done], [v["name"] for v in plan["variants"]]
    if names_there != names_now:
        differences.append(f"variants {','.join(names_there)} there vs {','.join(names_now)} now")
    elif done != plan["variants"]:
        differences.append("the variants' presets or changes differ")
    if bench.get("budget") != plan["budget"]:
        differences.append(f"budget {_budget_text(bench.get('budget'))} there vs {_budget_text(plan['budget'])} now")
    if bench.get("seed") != plan["seed"]:
        differences.append(f"seed {bench.get('seed')} there vs {plan['seed']} now")
    return differences


def _budget_text(budget: object) -> str:
    if isinstance(budget, dict) and "seconds" in budget:
        return f"{budget['seconds']:g} s"
    if isinstance(budget, dict) and "iterations" in budget:
        return f"{budget['iterations']} iterations"
    return repr(budget)


def _read_json(path: Path) -> dict | None:
    try:
        document = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return document if isinstance(document, dict) else None


def _check_folder(out_dir: Path, datasets: list[SuiteDataset], plan: dict, overwrite: bool) -> dict[str, dict]:
    """Refuse what must not be replaced (before anything runs); return the finished benches to keep."""
    if out_dir.exists() and not out_dir.is_dir():
        raise NerfError(f"{out_dir}: exists and is not a folder")
    if overwrite or not out_dir.is_dir() or not any(out_dir.iterdir()):
        return {}
    previous = _read_json(out_dir / PLAN_NAME)
    if previous is None:
        raise NerfError(f"{out_dir}: folder exists, is not empty and holds no suite bench ({PLAN_NAME}); "
                        "pass --overwrite to bench into it anyway")
    changed = [key for key in ("points", "curve_views", "device") if previous.get(key) != plan[key]]
    keep: dict[str, dict] = {}
    refusals = []
    for dataset in datasets:
        bench_json = out_dir / dataset.name / "bench.json"
        bench = _read_json(bench_json) if bench_json.is_file() else None
        if bench is None:
            continue  # not benched yet, or interrupted: benched (again)
        differences = _finished_bench_differences(bench, dataset, plan) + [
            f"{key} {previous.get(key)} there vs {plan[key]} now" for key in changed]
        if differences:
            refusals.append(f"{bench_json} ({'; '.join(differences)})")
        else:
            keep[dataset.name] = bench
    if refusals:
        raise NerfError(f"bench --suite: finished benches made with other settings: {', '.join(refusals)}; "
                        "rerun with the same settings or pass --overwrite to bench them again")
    return keep


def run_suite(paths: list[Path], variants: list[Variant], out_dir: Path, budget_seconds: float | None,
              iterations: int | None, points: int | tuple[float, ...] = 6, curve_views: int = 8, seed: int = 0,
              device: str = "auto", overwrite: bool = False, command: str | None = None) -> dict:
    """Bench every dataset of ``paths`` into ``out_dir/NAME`` and write the summary; return it.
    ``command``: the command line, recorded with the source's commit."""
    if (budget_seconds is None) == (iterations is None):
        raise NerfError("bench: give exactly one of --budget-seconds or --iters")
    datasets, skipped = find_datasets(paths)
    budget = {"seconds": budget_seconds} if budget_seconds is not None else {"iterations": iterations}
    plan = _plan(datasets, variants, budget, points, curve_views, seed, device)
    keep = _check_folder(out_dir, datasets, plan, overwrite)
    for path in skipped:
        print(f"bench --suite: skipping {path} (no {DATASET_MARKER}: not a finished dataset)", file=sys.stderr)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / PLAN_NAME, plan)
    scenes = []
    for number, dataset in enumerate(datasets, 1):
        label = f"bench --suite: [{number}/{len(datasets)}] {dataset.name}"
        scene_dir = out_dir / dataset.name
        if dataset.name in keep:
            print(f"{label}: finished bench kept ({scene_dir / 'bench.json'})", file=sys.stderr, flush=True)
            bench = keep[dataset.name]
        else:
            again = scene_dir.is_dir() and any(scene_dir.iterdir()) and not overwrite
            print(f"{label}: {'benching again (unfinished)' if again else 'benching'} {dataset.path} into "
                  f"{scene_dir}", file=sys.stderr, flush=True)
            # An unfinished scene folder holds no result to protect: it is redone.
            bench = run_bench(dataset.path, variants, scene_dir, budget_seconds, iterations, points=points,
                              curve_views=curve_views, seed=seed, device=device, overwrite=True, command=command)
        scenes.append(scene_summary(dataset, bench, scene_dir))
    summary = {
        "budget": budget, "seed": seed, "device": device,
        "machine": machine_record(resolve_device(device)),
        "provenance": provenance(command),
        "variants": plan["variants"],
        "collapse_margin_db": COLLAPSE_MARGIN_DB,
        "collapse_rule": {"detected": "the trainer logged a 'collapse' event (events.jsonl)",
                          "collapsed": f"final test PSNR < blank-image PSNR + {COLLAPSE_MARGIN_DB:g} dB"},
        "best_fixed_rule": "highest final test PSNR among the variants whose preset is not auto, same budget",
        "scenes": scenes,
    }
    write_json(out_dir / "summary.json", summary)
    (out_dir / "summary.md").write_text(suite_markdown(summary))
    plot_suite(summary, out_dir / "summary.png")
    return summary
