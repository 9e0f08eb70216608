"""``bench-step`` for marched presets (fast, auto, hash): one training step and one test view
rendered at the dataset's size, split by stage (``core.stage_timer``), each stage against what
this machine can do (``hardware.measure_hardware``): where the time goes, and how far each
stage is from its limit.

A stage's reference is the time its work takes at the machine's measured rates: the field's
gathers at the rate of random gathers from a table of the field's size plus its FLOPs at the
matrix-product rate (from the field's own ``sample_cost``), the optimiser's 7 float reads and
writes a parameter (Adam: p, g, m, v in; p, m, v out) and the march's 10 floats a sample (a
position, a length, a distance and an occupancy written and read) at the copy bandwidth.
"× reference" is the stage's time over that: far above 1, the stage spends its time on
something other than its necessary work (many small kernels, temporaries); below 1, its
gathers are kinder than random ones (samples along a ray share cache lines). Stages without
such a model have none; their share of the time still says what they cost."""

from __future__ import annotations

import time
from pathlib import Path

from ..core.devices import machine_record, machine_words, resolve_device
from ..core.errors import NerfError
from ..core.files import write_json
from ..core.stage_timer import StageTimer
from ..data.dataset import load_split
from ..data.run_folder import RunFolder
from ..evaluation.inference import load_trained_model
from ..evaluation.render_views import render_image
from ..fields.base import SampleCost
from ..training.trainer import TrainOptions, train
from .hardware import measure_hardware

# Training stages in the order a step runs them (trainer._step and marcher.render_marched).
TRAINING_STAGES = ("data", "rays", "upkeep", "march", "density pass", "field", "composite", "loss", "backward",
                   "optimiser")
# Rendering stages (marcher.render_marched_stopping_early); "other" is the rest of the view.
# The compiled march (compiled_march.py) does spans, march and density in one pass: "march".
RENDER_STAGES = ("spans", "march", "density", "colour")
COMPILED_RENDER_STAGES = ("march", "colour")
MARCH_BYTES_PER_SAMPLE = 10 * 4
ADAM_BYTES_PER_PARAMETER = 7 * 4


def _reference(cost: SampleCost, items: float, hardware: dict) -> float:
    return items * (cost.gathers / (hardware["gathers_m_s"] * 1e6) + cost.flops / (hardware["gflops"] * 1e9))


def _rows(seconds: dict, items: dict, references: dict, stages: tuple[str, ...], total: float, per: int) -> list[dict]:
    rows = []
    for name in (*stages, "other"):
        spent = (total * per - sum(seconds.get(s, 0.0) for s in stages)) if name == "other" else seconds.get(name, 0.0)
        reference = references.get(name)
        rows.append({"stage": name, "seconds": spent / per, "share": spent / (total * per) if total else 0.0,
                     "items": items.get(name, 0) / per if name != "other" else None,
                     "reference_seconds": reference / per if reference is not None else None,
                     "times_reference": spent / reference if reference else None})
    return rows


def profile_marched_step(dataset: Path, preset: str, steps: int, out_dir: Path, seed: int = 0,
                         warmup_seconds: float = 60.0, overrides: tuple[str, ...] = (), device_name: str = "auto",
                         overwrite: bool = False) -> dict:
    """Warm the preset up for ``warmup_seconds`` (its whole schedule laid over them, so the
    grid is at its final size and the occupancy grid has learnt the scene), time ``steps``
    more steps and one test view by stage, and write ``step_profile.json`` and ``.md``."""
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise NerfError(f"{out_dir}: bench folder exists and is not empty; pass --overwrite to replace it")
    out_dir.mkdir(parents=True, exist_ok=True)
    device = resolve_device(device_name)
    run_dir = out_dir / "runs" / preset
    common = dict(dataset=Path(dataset), run=run_dir, progress=False, validate=False, device=device_name)
    warm = train(TrainOptions(**common, preset=preset, overrides=overrides, seed=seed, max_seconds=warmup_seconds,
                              overwrite=True))
    with StageTimer(device) as timer:
        # At the end of the warm-up's schedule (its budget spent), with its time limit lifted.
        timed = train(TrainOptions(**common, iterations=warm.iteration + steps, resume=True,
                                   max_seconds=1e9, schedule_seconds=warmup_seconds))
    step_seconds = (timed.train_seconds - warm.train_seconds) / steps

    model, ray_bounds, _ = load_trained_model(RunFolder(run_dir), device)
    costs = model.field.sample_cost()
    hardware = measure_hardware(device, table_bytes=sum(p.numel() * 4 for p in model.field.encoding_parameters()))
    test = load_split(dataset, "test")
    render_image(model, test.intrinsics, test.poses[0], ray_bounds)  # untimed: caches (the density volume)
    with StageTimer(device) as render_timer:
        start = time.perf_counter()
        render_image(model, test.intrinsics, test.poses[0], ray_bounds)
        render_seconds = time.perf_counter() - start

    def bandwidth_reference(items: float, bytes_each: int) -> float:
        return items * bytes_each / (hardware["bandwidth_gb_s"] * 1e9)

    train_items, render_items = timer.items, render_timer.items
    field = costs["field"]
    train_references = {
        "march": bandwidth_reference(train_items["march"], MARCH_BYTES_PER_SAMPLE),
        "density pass": _reference(costs["frozen density"], train_items["density pass"], hardware),
        "field": _reference(field, train_items["field"], hardware),
        # Backward: every gathered value is scattered back (a read and a write), the FLOPs twice.
        "backward": _reference(SampleCost(2 * field.gathers, 2 * field.flops), train_items["field"], hardware),
        "optimiser": bandwidth_reference(train_items["optimiser"], ADAM_BYTES_PER_PARAMETER),
    }
    compiled = "spans" not in render_timer.seconds
    render_stages = COMPILED_RENDER_STAGES if compiled else RENDER_STAGES
    render_references = {
        "march": bandwidth_reference(render_items["march"], MARCH_BYTES_PER_SAMPLE),
        "colour": _reference(costs["colour"], render_items["colour"], hardware),
    }
    if not compiled:
        render_references["density"] = _reference(costs["frozen density"], render_items["density"], hardware)
    config = RunFolder(run_dir).read_config()
    report = {
        "dataset": str(Path(dataset).resolve()), "preset": preset, "overrides": list(overrides), "seed": seed,
        "device": str(device), "machine": machine_record(device),
        "hardware": hardware,
        "warmup": {"seconds": warm.train_seconds, "iterations": warm.iteration},
        "image_size": [test.intrinsics.width, test.intrinsics.height],
        "train_views": config["train_views"], "rays_per_batch": config["config"]["rays_per_batch"],
        "vertices": list(getattr(model.field, "vertices", ())) or None,
        "occupied_fraction": model.occupancy.occupied_fraction,
        "training": {"steps": steps, "seconds_per_step": step_seconds,
                     "stages": _rows(timer.seconds, train_items, train_references, TRAINING_STAGES, step_seconds, steps)},
        "render": {"view": 0, "seconds": render_seconds, "compiled_march": compiled,
                   "stages": _rows(render_timer.seconds, render_items, render_references, render_stages, render_seconds,
                                    1)},
        "reference_model": __doc__.split("\n\n", 1)[1].replace("\n", " ").strip(),
    }
    write_json(out_dir / "step_profile.json", report)
    (out_dir / "step_profile.md").write_text(profile_markdown(report))
    return report


def profile_markdown(report: dict) -> str:
    """The profile as two tables (training step, rendered view)."""
    hw = report["hardware"]
    lines = [f"# bench-step: {report['preset']} on {report['dataset']}", "",
             f"{report['image_size'][0]}×{report['image_size'][1]} images, {report['train_views']} train views, "
             f"{report['rays_per_batch']} rays a step, grid vertices {report['vertices']}, "
             f"{report['occupied_fraction']:.1%} of occupancy cells occupied; {report['device']}, "
             f"{machine_words(report['machine'])}.", "",
             f"This machine, measured: {hw['gflops']:.0f} GFLOP/s (float32 matrix product), "
             f"{hw['bandwidth_gb_s']:.1f} GB/s (copy), {hw['gathers_m_s']:.0f} M random float gathers/s from a "
             f"table of the field's size. \"× reference\": the stage's time over the time its work takes at those "
             f"rates (step_profile.py says how).", ""]
    for title, key, unit in (("Training step", "training", "step"), ("Rendered view", "render", "view")):
        part = report[key]
        total = part["seconds_per_step"] if key == "training" else part["seconds"]
        lines += [f"## {title}: {total * 1000:.1f} ms a {unit}", ""]
        if part.get("compiled_march"):
            lines += ["Through the compiled march: \"march\" is the spans, the fine steps, the density reads and "
                      "the compositing in one pass (its items: the fine steps looked up).", ""]
        lines += [
                  "| stage | ms | share | items | reference ms | × reference |",
                  "| --- | ---: | ---: | ---: | ---: | ---: |"]
        for row in part["stages"]:
            items = "" if row["items"] is None else f"{row['items']:,.0f}"
            reference = "—" if row["reference_seconds"] is None else f"{row['reference_seconds'] * 1000:.2f}"
            times = "—" if row["times_reference"] is None else f"{row['times_reference']:.1f}"
            lines.append(f"| {row['stage']} | {row['seconds'] * 1000:.2f} | {row['share']:.0%} | {items} | "
                         f"{reference} | {times} |")
        lines.append("")
    return "\n".join(lines)
