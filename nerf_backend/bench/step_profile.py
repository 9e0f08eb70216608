"""``bench-step`` for marched presets (fast, auto, hash, surface, plenoxels): one training step
and one test view rendered at the dataset's size, split by stage (``core.stage_timer``), each stage against what
this machine can do (``hardware.measure_hardware``): where the time goes, and how far each
stage is from its limit.

A stage's reference is a lower bound on the time its work takes at the machine's measured
rates, so "× reference" is about 1 or more and says how far the stage is from what the machine
allows. (Not quite a bound for the row-sparse optimiser on two threads: it visits its rows in
address order, prefetched, faster than the random lines its reference counts: 0.9× on lego at
800×800.) The work is counted three ways, and the reference is the largest of the three times:
- FLOPs (from the field's own ``sample_cost``: interpolation and networks; with deferred
  colour, the network once a shaded ray in training's "composite" and twice that in its
  backward) at the rate of a large float32 matrix product;
- bytes moved at the copy bandwidth: the march's 10 floats a sample (a position, a length, a
  distance and an occupancy written and read), the optimiser's 7 floats a value it updates
  (Adam: p, g, m, v in; p, m, v out; a row-sparse Adam updates only the rows a step touched);
- random cache lines gathered, at the measured rate of random 64-byte lines from a table of the
  field's size: the grid rows the step touched (the row-sparse optimiser counts them), each
  read once by the field's forward, and read and written again (values and gradients) by the
  backward (only written, for a voxel grid's blend: ``MarchableField.BACKWARD_WORK``), and
  by the optimiser in each of Adam's four arrays. Samples along a ray share rows, so rows, not
  samples times rows, are the floor. The rate is the faster of PyTorch's gather and a compiled
  loop's (``kernels/machine_rates.c``), so that it stays a lower bound.
A stage the model cannot bound has no reference; its share of the time still says what it costs.
The profile names the stage with the most time above its reference: where a step can gain most.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from nerf_contract.run_layout import CHECKPOINT_NAME, CONFIG_NAME, EVENTS_NAME

from ..core.cpu_steal import StealMeter, steal_note
from ..core.devices import machine_record, machine_words, resolve_device
from ..configs.presets import preset_config
from ..core.errors import NerfError
from ..core.files import write_json
from ..core.provenance import source_commit
from ..core.stage_timer import StageTimer
from ..data.dataset import load_split
from ..data.run_folder import RunFolder
from ..evaluation.inference import load_trained_model
from ..evaluation.render_views import render_image
from ..models.marched import MarchedModel
from ..models.registry import model_class
from ..training.trainer import TrainOptions, train
from ..model_components.compiled_march import COMPILED_TRAINING_MARCH
from ..model_components.marcher import COMPILED_LIT_PASS, SHADED_RAYS
from .hardware import LINE_FLOATS, measure_hardware

# Training stages in the order a step runs them (trainer._step and marcher.render_marched).
TRAINING_STAGES = ("data", "rays", "upkeep", "march", "density pass", "field", "composite", "loss", "backward",
                   "optimiser")
# Rendering stages (marcher.render_marched_stopping_early); "other" is the rest of the view.
# The compiled march (compiled_march.py) does spans, march and density in one pass: "march";
# then "shade", each ray's colour from what it composited (deferred colour's network).
RENDER_STAGES = ("spans", "march", "density", "colour")
COMPILED_RENDER_STAGES = ("march", "colour", "shade")
MARCH_BYTES_PER_SAMPLE = 10 * 4
ADAM_BYTES_PER_VALUE = 7 * 4
# Adam's touched rows lie scattered: value, gradient and the two moments, a random line each a row of 16.
ADAM_ARRAYS = 4
# Steps timed at the least: the default is the fewest whole periods of the occupancy refresh.
DEFAULT_STEPS = 50
# What a profile keeps of the earlier one it is shown beside (--before).
BEFORE_KEYS = ("commit", "warmup", "vertices", "hardware", "training", "render")


def _reference(hardware: dict, flops: float = 0.0, bytes_moved: float = 0.0, lines: float = 0.0) -> float:
    """The time the work takes at the best of the machine's measured rates: the largest of its
    FLOPs', its bytes' and its random cache lines' times (a lower bound on the stage's time)."""
    return max(flops / (hardware["gflops"] * 1e9), bytes_moved / (hardware["bandwidth_gb_s"] * 1e9),
               lines / (hardware["lines_m_s"] * 1e6))


def farthest_from_limit(rows: list[dict]) -> dict | None:
    """The stage with the most time above its reference (None if no stage has one).

    Example:
        >>> farthest_from_limit([{"stage": "a", "seconds": 2.0, "reference_seconds": 1.0},
        ...                      {"stage": "b", "seconds": 9.0, "reference_seconds": 8.5}])["stage"]
        'a'
    """
    bounded = [row for row in rows if row.get("reference_seconds")]
    return max(bounded, key=lambda row: row["seconds"] - row["reference_seconds"], default=None)


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


def profile_marched_step(dataset: Path, preset: str, steps: int | None, out_dir: Path, seed: int = 0,
                         warmup_seconds: float = 60.0, overrides: tuple[str, ...] = (), device_name: str = "auto",
                         overwrite: bool = False, from_run: Path | None = None, before: Path | None = None) -> dict:
    """Warm the preset up for ``warmup_seconds`` (its whole schedule laid over them, so the
    grid is at its final size and the occupancy grid has learnt the scene), time ``steps``
    more steps and one test view by stage, and write ``step_profile.json`` and ``.md``.
    ``steps`` None: the fewest whole periods of the occupancy grid's refresh that make at least
    ``DEFAULT_STEPS`` (a refresh of lego's 255³ cells costs 0.3 s once in 67 steps: 4-6 ms a
    step, which 50 steps timed held once or not at all).

    ``from_run``: no warm-up; the steps continue a copy of that trained run (its preset, its
    grid, its place in its schedule), so that two versions of the code time the same state, which
    a warm-up of so many seconds does not give them (the faster one reaches a larger grid).
    ``before``: another profile's ``step_profile.json``, shown beside this one stage by stage
    (the before and after of a change, side by side)."""
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise NerfError(f"{out_dir}: bench folder exists and is not empty; pass --overwrite to replace it")
    earlier = read_profile(before) if before is not None else None
    origin = trained_start(from_run, Path(dataset)) if from_run is not None else None
    if origin is not None:
        preset = origin.preset
    out_dir.mkdir(parents=True, exist_ok=True)
    device = resolve_device(device_name)
    run_dir = out_dir / "runs" / preset
    common = dict(dataset=Path(dataset), run=run_dir, progress=False, validate=False, device=device_name)
    origin = origin.copy_to(run_dir) if origin is not None else warmed_up(common, preset, overrides, seed,
                                                                            warmup_seconds)
    refresh_every = load_trained_model(RunFolder(run_dir), device)[0].occupancy_refresh_every()
    steps = steps or refresh_every * math.ceil(DEFAULT_STEPS / refresh_every)
    step_seconds, timer, training_steal = _timed_steps(origin, steps, common, device)

    model, ray_bounds, _ = load_trained_model(RunFolder(run_dir), device)
    costs = model.field.sample_cost()
    hardware = measure_hardware(device, table_bytes=sum(p.numel() * 4 for p in model.field.encoding_parameters()))
    test = load_split(dataset, "test")
    render_image(model, test.intrinsics, test.poses[0], ray_bounds)  # untimed: caches (the density volume)
    with StageTimer(device) as render_timer, StealMeter() as render_steal:
        start = time.perf_counter()
        render_image(model, test.intrinsics, test.poses[0], ray_bounds)
        render_seconds = time.perf_counter() - start

    train_items, render_items = timer.items, render_timer.items
    train_references = _training_references(hardware, train_items, costs, model.field.BACKWARD_WORK)
    compiled_training = bool(train_items.get(COMPILED_TRAINING_MARCH))
    compiled = "spans" not in render_timer.seconds
    render_stages = COMPILED_RENDER_STAGES if compiled else RENDER_STAGES
    render_references = _render_references(hardware, render_items, costs, compiled)
    config = RunFolder(run_dir).read_config()
    report = {
        "dataset": str(Path(dataset).resolve()), "preset": preset, "overrides": list(overrides), "seed": seed,
        "device": str(device), "machine": machine_record(device),
        "hardware": hardware,
        "warmup": {"seconds": origin.train_seconds, "iterations": origin.iteration,
                   "from_run": None if origin.source is None else str(origin.source.resolve())},
        "commit": source_commit(),
        "image_size": [test.intrinsics.width, test.intrinsics.height],
        "train_views": config["train_views"], "rays_per_batch": config["config"]["rays_per_batch"],
        "vertices": list(getattr(model.field, "vertices", ())) or None,
        "occupied_fraction": model.occupancy.occupied_fraction,
        "training": {"steps": steps, "occupancy_refresh_every": refresh_every, "seconds_per_step": step_seconds,
                     "compiled_march": compiled_training, "cpu_stolen_share": training_steal.share,
                     "stages": _rows(timer.seconds, train_items, train_references, TRAINING_STAGES, step_seconds,
                                     steps)},
        "render": {"view": 0, "seconds": render_seconds, "compiled_march": compiled,
                   "cpu_stolen_share": render_steal.share,
                   "stages": _rows(render_timer.seconds, render_items, render_references, render_stages, render_seconds,
                                    1)},
        "reference_model": __doc__.split("\n\n", 1)[1].replace("\n", " ").strip(),
    }
    if earlier is not None:
        report["before"] = {**{key: earlier.get(key) for key in BEFORE_KEYS}, "path": str(Path(before).resolve())}
    write_json(out_dir / "step_profile.json", report)
    (out_dir / "step_profile.md").write_text(profile_markdown(report))
    return report


def _timed_steps(origin: "TrainedStart", steps: int, common: dict, device) -> tuple[float, StageTimer, StealMeter]:
    """``steps`` more steps of the run, by stage: at the end of its schedule (its budget spent),
    with its time limit lifted. Returns the seconds a step, the stages' timer and the steal."""
    with StageTimer(device) as timer, StealMeter() as steal:
        timed = train(TrainOptions(**common, iterations=origin.iteration + steps, resume=True,
                                   max_seconds=1e9, schedule_seconds=origin.schedule_seconds))
    return (timed.train_seconds - origin.train_seconds) / steps, timer, steal


@dataclass(frozen=True)
class TrainedStart:
    """Where the timed steps begin: a warm-up just trained, or a copy of a trained run."""

    preset: str
    iteration: int
    train_seconds: float
    schedule_seconds: float | None  # the time budget its schedule is laid over (None: by iterations)
    source: Path | None  # the run it was copied from

    def copy_to(self, run_dir: Path) -> "TrainedStart":
        """The run's configuration, checkpoint and log into ``run_dir`` (not its renders): the
        copy trains on, the run itself is left as it was."""
        run_dir.mkdir(parents=True, exist_ok=True)
        for name in (CONFIG_NAME, CHECKPOINT_NAME, EVENTS_NAME):
            if (self.source / name).exists():
                shutil.copyfile(self.source / name, run_dir / name)
        return self


def warmed_up(common: dict, preset: str, overrides: tuple[str, ...], seed: int, seconds: float) -> TrainedStart:
    """A new run of ``preset`` trained for ``seconds``, its whole schedule laid over them."""
    warm = train(TrainOptions(**common, preset=preset, overrides=overrides, seed=seed, max_seconds=seconds,
                              overwrite=True))
    return TrainedStart(preset, warm.iteration, warm.train_seconds, seconds, None)


def trained_start(run: Path, dataset: Path) -> TrainedStart:
    """A trained run to time steps from on ``dataset`` (``bench-step --from-run``), or NerfError
    naming the folder and what does not fit."""
    folder = RunFolder(run)
    config = folder.read_config()
    if Path(config["dataset"]) != dataset.resolve():
        raise NerfError(f"{run}: trained on {config['dataset']}, not {dataset}; --from-run continues it on its own "
                        f"dataset")
    if not folder.checkpoint_path.exists():
        raise NerfError(f"{run}: no {CHECKPOINT_NAME}; --from-run takes a trained run folder")
    model = model_class(preset_config(config["preset"]).model)
    if not issubclass(model, MarchedModel):
        raise NerfError(f"{run}: its preset {config['preset']!r} is not a marched one; bench-step profiles "
                        f"marched presets by stage")
    state = folder.load_checkpoint(torch.device("cpu"), mapped=True)
    return TrainedStart(config["preset"], int(state["iteration"]), float(state["train_seconds"]),
                        config.get("schedule_seconds") or config.get("max_seconds"), Path(run))


def read_profile(path: Path) -> dict:
    """An earlier ``step_profile.json``, or NerfError naming the file and what is wrong with it."""
    try:
        report = json.loads(Path(path).read_text())
    except OSError as exc:
        raise NerfError(f"{path}: cannot read it ({exc.strerror or exc}); --before takes step_profile.json") from None
    except json.JSONDecodeError as exc:
        raise NerfError(f"{path}: not JSON (line {exc.lineno}: {exc.msg}); --before takes step_profile.json") from None
    if not isinstance(report, dict) or not all(isinstance(report.get(key), dict) and "stages" in report[key]
                                               for key in ("training", "render")):
        raise NerfError(f"{path}: not a marched preset's bench-step profile (no training and render stages)")
    return report


def _render_references(hardware: dict, items: dict, costs: dict, compiled: bool) -> dict:
    """Each rendering stage's least time for its work at the machine's measured rates."""
    references = {"march": _reference(hardware, bytes_moved=items["march"] * MARCH_BYTES_PER_SAMPLE),
                  "colour": _reference(hardware, flops=items["colour"] * costs["colour"].flops)}
    if not compiled:
        references["density"] = _reference(hardware, flops=items["density"] * costs["density"].flops)
    elif "shade" in costs:  # deferred colour's network, once a shaded ray
        references["shade"] = _reference(hardware, flops=items.get("shade", 0) * costs["shade"].flops)
    return references


def _training_references(hardware: dict, items: dict, costs: dict, backward_work: float) -> dict:
    """Each training stage's least time for its work at the machine's measured rates."""
    colour_flops = costs["colour"].flops
    # Density at every lit sample; colour only at those the march found weighty, where it says.
    coloured = items.get("coloured samples", items["field"])
    field_work = items["field"] * costs["density"].flops + coloured * colour_flops
    # A field's lit pass takes the density the march read: its forward reads the colour's grid alone.
    forward_work = coloured * colour_flops if items.get(COMPILED_LIT_PASS) else field_work
    grid_lines = items.get("grid values", 0) / LINE_FLOATS  # the rows the step touched
    density_flops = items["density pass"] * costs["density"].flops
    # The compiled training march does the density pass inside its own pass: its reads count there.
    compiled_training = bool(items.get(COMPILED_TRAINING_MARCH))
    # Deferred colour: the network once a shaded ray in "composite", twice that backward.
    shade_flops = items.get(SHADED_RAYS, 0) * costs["shade"].flops if "shade" in costs else 0.0
    return {
        "march": _reference(hardware, bytes_moved=items["march"] * MARCH_BYTES_PER_SAMPLE,
                            flops=density_flops if compiled_training else 0.0),
        "density pass": None if compiled_training else _reference(hardware, flops=density_flops),
        "field": _reference(hardware, flops=forward_work, lines=grid_lines),
        # Backward: the forward's FLOPs twice over, the rows read again and their gradients
        # written; a voxel grid's blend only writes its gradients (BACKWARD_WORK).
        "composite": _reference(hardware, flops=shade_flops) if shade_flops else None,
        "backward": _reference(hardware, flops=backward_work * field_work + 2 * shade_flops,
                               lines=backward_work * grid_lines),
        "optimiser": _reference(hardware, bytes_moved=items["optimiser"] * ADAM_BYTES_PER_VALUE,
                                lines=ADAM_ARRAYS * grid_lines),
    }


def profile_markdown(report: dict) -> str:
    """The profile as two tables (training step, rendered view)."""
    hw = report["hardware"]
    lines = [f"# bench-step: {report['preset']} on {report['dataset']}", "",
             f"{report['image_size'][0]}×{report['image_size'][1]} images, {report['train_views']} train views, "
             f"{report['rays_per_batch']} rays a step, grid vertices {report['vertices']}, "
             f"{report['occupied_fraction']:.1%} of occupancy cells occupied; {report['device']}, "
             f"{machine_words(report['machine'])}.", "",
             f"This machine, measured: {hw['gflops']:.0f} GFLOP/s (float32 matrix product), "
             f"{hw['bandwidth_gb_s']:.1f} GB/s (copy), {hw['lines_m_s']:.0f} M random 64-byte cache lines/s from a "
             f"table of the field's size. \"× reference\": the stage's time over the least time its work (FLOPs, "
             f"bytes, cache lines) takes at those rates, about 1 or more (step_profile.py says how).", ""]
    for title, key, unit in (("Training step", "training", "step"), ("Rendered view", "render", "view")):
        part = report[key]
        total = part["seconds_per_step"] if key == "training" else part["seconds"]
        lines += [f"## {title}: {total * 1000:.1f} ms a {unit}", ""]
        if steal_note(part.get("cpu_stolen_share")):
            lines += [steal_note(part.get("cpu_stolen_share")), ""]
        if key == "training" and part.get("occupancy_refresh_every"):
            lines += [f"{part['steps']} steps timed; the occupancy grid is refreshed once in "
                      f"{part['occupancy_refresh_every']} (its cost is in \"upkeep\").", ""]
        if part.get("compiled_march") and key == "render":
            lines += ["Through the compiled march: \"march\" is the spans, the fine steps, the density reads and "
                      "the compositing in one pass (its items: the fine steps looked up).", ""]
        elif part.get("compiled_march"):
            lines += ["Through the compiled training march: \"march\" is the fine steps, the occupancy, the "
                      "density reads and the early stop in one pass a ray; \"density pass\" only counts its "
                      "density reads.", ""]
        lines += [
                  "| stage | ms | share | items | reference ms | × reference |",
                  "| --- | ---: | ---: | ---: | ---: | ---: |"]
        for row in part["stages"]:
            items = "" if row["items"] is None else f"{row['items']:,.0f}"
            reference = "—" if row["reference_seconds"] is None else f"{row['reference_seconds'] * 1000:.2f}"
            times = "—" if row["times_reference"] is None else f"{row['times_reference']:.1f}"
            lines.append(f"| {row['stage']} | {row['seconds'] * 1000:.2f} | {row['share']:.0%} | {items} | "
                         f"{reference} | {times} |")
        farthest = farthest_from_limit(part["stages"])
        if farthest is not None:
            lines += ["", f"Farthest from its limit: {farthest['stage']}, "
                          f"{(farthest['seconds'] - farthest['reference_seconds']) * 1000:.2f} ms above its reference "
                          f"({farthest['times_reference']:.1f}×)."]
        if report.get("before"):
            lines += [""] + before_and_after(report, key, unit)
        lines.append("")
    return "\n".join(lines)


def before_and_after(report: dict, key: str, unit: str) -> list[str]:
    """The ``before`` profile's stages beside this one's, for the training step or the view
    (``key``), and whether the two started from the same state."""
    before = report["before"]
    part, earlier = report[key], before[key]
    total = part["seconds_per_step"] if key == "training" else part["seconds"]
    total_before = earlier["seconds_per_step"] if key == "training" else earlier["seconds"]
    rows = {row["stage"]: row for row in earlier["stages"]}
    lines = [f"Before ({before.get('commit') or 'commit not recorded'}) and after "
             f"({report.get('commit') or 'commit not recorded'}): {total_before * 1000:.1f} → {total * 1000:.1f} ms a "
             f"{unit} ({total / total_before:.2f}×).", ""]
    started = before.get("warmup", {})
    same = (started.get("iterations") == report["warmup"]["iterations"] and before.get("vertices") == report["vertices"]
            and started.get("from_run") == report["warmup"].get("from_run"))
    if same:
        # The same work: both against this run's references, so that the rates' own noise between
        # the two measurements (a tenth to a third on the VMs here) does not move the comparison.
        lines += ["Both × reference columns at this run's measured rates (the two did the same work, from the "
                  "same start).", ""]
    else:
        lines += [f"Not side by side: the before started at iteration {started.get('iterations')} "
                  f"with grid vertices {before.get('vertices')} (from {started.get('from_run') or 'a warm-up'}), this "
                  f"one at {report['warmup']['iterations']} with {report['vertices']} (from "
                  f"{report['warmup'].get('from_run') or 'a warm-up'}); `--from-run` starts both from the same run.",
                  ""]
    lines += ["| stage | before ms | after ms | after / before | × reference before | × reference after |",
              "| --- | ---: | ---: | ---: | ---: | ---: |"]

    def times(seconds: float, row: dict | None) -> str:
        reference = None if row is None else row.get("reference_seconds")
        return "—" if not reference else f"{seconds / reference:.1f}"

    for row in part["stages"]:
        old = rows.get(row["stage"])
        old_ms = "—" if old is None else f"{old['seconds'] * 1000:.2f}"
        ratio = "—" if old is None or old["seconds"] <= 0 else f"{row['seconds'] / old['seconds']:.2f}"
        old_times = "—" if old is None else times(old["seconds"], row if same else old)
        lines.append(f"| {row['stage']} | {old_ms} | {row['seconds'] * 1000:.2f} | {ratio} | {old_times} | "
                     f"{times(row['seconds'], row)} |")
    return lines
