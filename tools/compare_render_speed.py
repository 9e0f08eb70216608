"""Render speed, side by side in one process: the inference march and grid reads of an earlier
commit against the working tree's, on the same trained run, the same test views and the same
threads.

    python tools/compare_render_speed.py RUN DATASET [--baseline b4fbebe] [--views 0,5,10,15]
                                         [--baseline-compiled]

Each side renders every view twice over (alternating, so both meet the same machine); the
median seconds per view, the mean PSNR against the dataset's test views and the largest pixel
difference between the two sides are printed. The baseline's ``marcher.py`` and
``occupancy.py`` are read with ``git show`` and loaded beside the current ones: where its
``occupancy.py`` differs from today's, the baseline marches the model's training occupancy grid
with its own skip grid, the current side what the model renders with today
(``render_occupancy``); where it is the same, both march ``render_occupancy``. The baseline's
``VectorMatrixGrid.forward`` (``field_components/grid_encodings.py``) reads the same grids on its
side. The baseline renders through PyTorch's march (the baseline's own), or with
``--baseline-compiled`` through the baseline's ``compiled_march.py`` (today's kernel); the current
side renders as the model does today: through the compiled march (``kernels/march_render.c``)
where it applies. A baseline march that takes ``colour_fn(points, directions)`` (before
``ray_colour``) is given the field's ``colour``. The model is the same.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import nerf_backend.model_components.marcher as marcher  # noqa: E402
import nerf_backend.models.marched as marched  # noqa: E402
from nerf_backend.core import field_functions  # noqa: E402
from nerf_backend.data.dataset import load_split  # noqa: E402
from nerf_backend.data.run_folder import RunFolder  # noqa: E402
from nerf_backend.evaluation.inference import load_trained_model  # noqa: E402
from nerf_backend.evaluation.render_views import render_image  # noqa: E402
from nerf_backend.field_components.grid_encodings import VectorMatrixGrid  # noqa: E402
from nerf_backend.metrics.image_metrics import psnr  # noqa: E402


def _load_baseline(revision: str, relative: str, name: str):
    """The module at ``nerf_backend/RELATIVE`` as it was at ``revision``, loaded as a module of
    the package (so its relative imports resolve to today's helpers)."""
    source = subprocess.run(["git", "show", f"{revision}:nerf_backend/{relative}"], cwd=ROOT,
                            check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / Path(relative).name
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def baseline_march(revision: str, model):
    """``render_marched_stopping_early`` as it was at ``revision``: over the model's training
    occupancy grid held in that revision's ``OccupancyGrid`` where that class has changed since."""
    occupancy = _load_baseline(revision, "model_components/occupancy.py",
                               "nerf_backend.model_components._baseline_occupancy")
    march = with_colour_fn(_load_baseline(revision, "model_components/marcher.py",
                                          "nerf_backend.model_components._baseline_marcher").render_marched_stopping_early,
                           model)
    current = (ROOT / "nerf_backend/model_components/occupancy.py").read_text()
    if Path(occupancy.__file__).read_text() == current:
        return march
    trained = model.occupancy
    grid = occupancy.OccupancyGrid(trained.box_min, trained.box_max, trained.cells).to(trained.occupied.device)
    grid.occupied.copy_(trained.occupied)

    def render(*args, occupancy, **kwargs):
        return march(*args, occupancy=grid, **kwargs)

    return render


def with_colour_fn(march, model):
    """``march`` as the model calls it today (``ray_colour=``, ``density_fn(points, directions)``),
    where the baseline's march took ``colour_fn(points, directions)`` and ``density_fn(points)``
    instead: it gets the field's ``colour`` and a density that needs no direction."""
    if "colour_fn" not in inspect.signature(march).parameters:
        return march

    def render(*args, ray_colour, density_fn=None, **kwargs):
        if density_fn is not None:  # the compiled march reads its density volume instead
            kwargs["density_fn"] = lambda x, directions=None: density_fn(x, directions)
        return march(*args, colour_fn=model.field.colour, **kwargs)

    return render


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--baseline", default="b4fbebe", help="the commit to compare with (default: before issue 24)")
    parser.add_argument("--views", default="0,5,10,15")
    parser.add_argument("--baseline-compiled", action="store_true",
                        help="the baseline renders through its own compiled march, not PyTorch's")
    args = parser.parse_args()
    model, ray_bounds, _ = load_trained_model(RunFolder(args.run), torch.device("cpu"))
    split = load_split(args.dataset, "test")
    views = [int(v) for v in args.views.split(",")]
    sides = {"baseline": baseline_march(args.baseline, model),
             "current": marched.render_marched_stopping_early}
    compiled = {"baseline": marched.render_marched_compiled, "current": marched.render_marched_compiled}
    if args.baseline_compiled:
        # Baselines before core/field_functions.py imported ColourFn from the marcher.
        marcher.ColourFn = field_functions.ColourFn
        compiled["baseline"] = with_colour_fn(_load_baseline(
            args.baseline, "model_components/compiled_march.py",
            "nerf_backend.model_components._baseline_compiled_march").render_marched_compiled, model)
    grid_reads = {"baseline": _load_baseline(args.baseline, "field_components/grid_encodings.py",
                                             "nerf_backend.field_components._baseline_grid_encodings"
                                             ).VectorMatrixGrid.forward,
                  "current": VectorMatrixGrid.forward}
    library = {"baseline": marched.compiled_march_library if args.baseline_compiled
               else (lambda: (None, "the baseline side")), "current": marched.compiled_march_library}
    seconds: dict[str, list[float]] = {name: [] for name in sides}
    images: dict[str, list[np.ndarray]] = {name: [] for name in sides}
    for repeat in range(2):
        for name, march in sides.items():
            marched.render_marched_stopping_early = march
            marched.render_marched_compiled = compiled[name]
            VectorMatrixGrid.forward = grid_reads[name]
            marched.compiled_march_library = library[name]
            for view in views:
                start = time.perf_counter()
                image = render_image(model, split.intrinsics, split.poses[view], ray_bounds)
                seconds[name].append(time.perf_counter() - start)
                if repeat == 0:
                    images[name].append(image.rgb)
    marched.render_marched_stopping_early = sides["current"]
    marched.render_marched_compiled = compiled["current"]
    VectorMatrixGrid.forward = grid_reads["current"]
    marched.compiled_march_library = library["current"]
    width, height = split.intrinsics.width, split.intrinsics.height
    print(f"{args.run} on {args.dataset}: {width}×{height}, views {views}, {torch.get_num_threads()} threads")
    for name in sides:
        scores = [psnr(image, split.rgb_on_white(view).numpy()) for image, view in zip(images[name], views)]
        print(f"  {name:8s} median {statistics.median(seconds[name]):.3f} s a view "
              f"(all: {', '.join(f'{s:.2f}' for s in seconds[name])}), mean PSNR {np.mean(scores):.3f} dB")
    ratio = statistics.median(seconds["baseline"]) / statistics.median(seconds["current"])
    difference = max(float(np.abs(a - b).max()) for a, b in zip(images["baseline"], images["current"]))
    print(f"  speed-up {ratio:.2f}×; largest pixel difference {difference:.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
