"""``bench-kilonerf RUN``: KiloNeRF measured for the live view. The run's model (the teacher)
is distilled into a grid of tiny networks (``fields/kilo_field.py``) for a time budget, then
both render the dataset's first test views through the same march (the teacher's occupancy
grid, early termination) at the full size and a quarter of it, on the same device.

Distillation follows the paper's first stage: points drawn in the teacher's occupied cells,
random view directions, an L2 loss on each sample's opacity over one march step and on its
colour (weighted by the teacher's opacity: a colour nobody sees does not count). The paper's
second stage (fine-tuning on the images) is left out: it would cost the student as much
training time again.

Reported: distillation seconds, each model's PSNR on the views, its time a frame at both sizes,
its parameters' bytes, and the floating-point work a sample costs the student.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from ..core.devices import colour_network_dtype, machine_record, machine_words
from ..core.errors import NerfError
from ..core.files import write_json
from ..data.dataset import load_split
from ..data.run_folder import RunFolder
from ..evaluation.inference import load_trained_model
from ..evaluation.render_views import render_image
from ..fields.kilo_field import KiloNerf, cells_for_box
from ..metrics.image_metrics import psnr
from ..model_components.marcher import render_marched_stopping_early
from ..model_components.render_output import RenderOutput
from ..models.marched import MarchedModel
from ..training.adam import Adam

BATCH = 16384  # distillation samples a step


class MarchedFunctions(nn.Module):
    """A density function and a colour function marched as ``teacher`` marches (its occupancy
    grid and step, PyTorch's march with early termination): a model ``render_image`` renders.
    The student is rendered this way, and the teacher too, for a comparison of the fields alone
    (the product's renderer runs the teacher through its compiled march)."""

    def __init__(self, owner: nn.Module, density_fn, ray_colour, teacher) -> None:
        super().__init__()
        self.owner = owner  # the module the functions belong to: its parameters say the device
        self.density_fn, self.ray_colour, self.occupancy = density_fn, ray_colour, teacher.render_occupancy()
        self.step, self.steps = teacher.step, teacher.samples_per_ray
        self.render_chunk = teacher.TORCH_RENDER_CHUNK

    def forward(self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
                background: Tensor | float = 1.0) -> list[RenderOutput]:
        return [render_marched_stopping_early(
            origins, directions, t_near, t_far, density_fn=self.density_fn, ray_colour=self.ray_colour(directions),
            occupancy=self.occupancy, step=self.step, steps=self.steps, background=background)]


def distil(teacher, cells: tuple[int, int, int], seconds: float, seed: int = 0,
           on_step=None) -> tuple[KiloNerf, dict]:
    """The student after ``seconds`` of distillation from ``teacher`` (a marched model)."""
    device = next(teacher.parameters()).device
    generator = torch.Generator(device=device).manual_seed(seed)
    torch.manual_seed(seed)
    occupancy = teacher.render_occupancy()
    student = KiloNerf(teacher.field.box, cells).to(device)
    optimiser = Adam([{"params": student.parameters(), "lr": 5e-3}])
    occupied = occupancy.occupied.nonzero().float()
    cell_size = (occupancy.box_max - occupancy.box_min) / torch.tensor(occupancy.cells, device=device)
    start, steps, losses = time.perf_counter(), 0, []
    while time.perf_counter() - start < seconds:
        pick = torch.randint(occupied.shape[0], (BATCH,), generator=generator, device=device)
        points = occupancy.box_min + (occupied[pick] + torch.rand((BATCH, 3), generator=generator, device=device)) * cell_size
        directions = nn.functional.normalize(torch.randn((BATCH, 3), generator=generator, device=device), dim=-1)
        with torch.no_grad():
            alpha_t = 1 - torch.exp(-teacher.field.density_along(points, directions) * teacher.step)
            colour_t = teacher.field.colour(points, directions)
        density, colour = student(points, directions)
        alpha = 1 - torch.exp(-density * teacher.step)
        loss = ((alpha - alpha_t) ** 2).mean() + (alpha_t[:, None] * (colour - colour_t) ** 2).mean()
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        steps += 1
        losses.append(float(loss.detach()))
        if on_step is not None:
            on_step(time.perf_counter() - start, seconds)
    return student, {"seconds": time.perf_counter() - start, "steps": steps, "batch": BATCH,
                     "final_loss": statistics.mean(losses[-20:]) if losses else None}


def _frame_seconds(model, intrinsics, pose, ray_bounds, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        render_image(model, intrinsics, pose, ray_bounds)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _bytes(module: nn.Module) -> int:
    return sum(p.numel() * p.element_size() for p in module.parameters()) + sum(
        b.numel() * b.element_size() for b in module.buffers())


def kilonerf_trade(run: Path, out_dir: Path, seconds: float, cells: tuple[int, int, int] | None = None,
                   views: int = 3, device: str = "cpu", on_step=None) -> dict:
    """Distils ``run`` and measures both models (see the module's text); writes
    ``kilonerf.json`` and ``kilonerf.md`` into ``out_dir``."""
    folder = RunFolder(run)
    teacher, ray_bounds, state = load_trained_model(folder, torch.device(device))
    if not isinstance(teacher, MarchedModel):
        raise NerfError(f"{run}: bench-kilonerf distils a marched model (the auto, fast, plenoxels or hash preset); "
                        f"this run's is {type(teacher).__name__}")
    cells = cells or cells_for_box(teacher.field.box)
    student, distillation = distil(teacher, cells, seconds, on_step=on_step)
    test = load_split(folder.read_config()["dataset"], "test").subset(views)
    quarter = test.intrinsics.scaled(0.25)
    rows = {}
    device_type = torch.device(device)
    contenders = (
        ("the run's model, the product's renderer", teacher, teacher),
        ("the run's model, PyTorch's march", MarchedFunctions(
            teacher, teacher._frozen_density, lambda d: teacher.field.ray_colour(d, colour_network_dtype(device_type)), teacher),
         teacher),
        ("KiloNeRF", MarchedFunctions(student, student.density_fn, student.ray_colour, teacher), student))
    for name, model, owner in contenders:
        scores = [psnr(render_image(model, test.intrinsics, test.poses[i], ray_bounds).rgb, test.rgb_on_white(i).numpy())
                  for i in range(len(test))]
        rows[name] = {"psnr": float(np.mean(scores)),
                      "full_seconds": _frame_seconds(model, test.intrinsics, test.poses[0], ray_bounds, 2),
                      "quarter_seconds": _frame_seconds(model, quarter, test.poses[0], ray_bounds, 5),
                      "bytes": _bytes(owner)}
    report = {"run": str(Path(run).resolve()), "iteration": state["iteration"], "device": device,
              "machine": machine_record(torch.device(device)), "cells": list(cells), "views": len(test),
              "size": [test.intrinsics.width, test.intrinsics.height], "distillation": distillation,
              "student_flops_per_sample": student.flops_per_sample(), "models": rows}
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "kilonerf.json", report)
    (out_dir / "kilonerf.md").write_text(kilonerf_markdown(report))
    return report


def kilonerf_markdown(report: dict) -> str:
    width, height = report["size"]
    distillation, flops = report["distillation"], report["student_flops_per_sample"]
    lines = [f"# bench-kilonerf: {report['run']} (iteration {report['iteration']})", "",
             f"{report['device']}, {machine_words(report['machine'])}; {report['views']} test views at {width}×{height}; "
             f"KiloNeRF of {'×'.join(map(str, report['cells']))} cells distilled for {distillation['seconds']:.0f} s "
             f"({distillation['steps']} steps of {distillation['batch']} points); a sample costs it "
             f"{flops['density'] / 1e3:.1f} kFLOP for density, {flops['colour'] / 1e3:.1f} for colour.", "",
             f"| model | PSNR (dB) | frame {width}×{height} (s) | frame {width // 4}×{height // 4} (s) | parameters (MB) |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for name, row in report["models"].items():
        lines.append(f"| {name} | {row['psnr']:.2f} | {row['full_seconds']:.2f} | {row['quarter_seconds']:.3f} | "
                     f"{row['bytes'] / 1e6:.1f} |")
    return "\n".join(lines) + "\n"
