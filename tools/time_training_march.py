"""The compiled training march alone (``kernels/train_march.h``'s ``march_train``), timed on a
trained run's occupancy grid and density with batches of its dataset's training rays: what
``bench-step``'s "march" stage holds without the rest of a step, on the run's fixed state
(as ``bench-step --from-run RUN`` times the whole step; without it, ``bench-step`` trains for a
time first, so two codes reach different grids).

    python tools/time_training_march.py RUN DATASET [--rays 2048] [--batches 40] [--repeats 8]
                                        [--threads 2]

Prints the median, the tenth percentile and the fastest seconds of a batch, and the lit samples
a batch found (equal between two codes that march alike). Two codes side by side: run it with
each checkout on PYTHONPATH in turn, more than once (this machine's speed drifts)."""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from nerf_backend.core.cameras import camera_rays, pixel_centres, ray_box_intersection
from nerf_backend.data.dataset import load_split
from nerf_backend.data.run_folder import RunFolder
from nerf_backend.evaluation.inference import load_trained_model
from nerf_backend.model_components.compiled_march import compiled_lit_samples


def training_batches(run: Path, dataset: Path, rays: int, batches: int, seed: int = 0):
    """The run's training march (``compiled_lit_samples``) and ``batches`` batches of ``rays``
    random training rays, each cut to the occupancy grid's box and given a random offset."""
    model, _, _ = load_trained_model(RunFolder(run), torch.device("cpu"))
    density = model.field.compiled_density()
    if density is None:
        raise SystemExit(f"{run}: its density has no compiled read here (no C compiler, or not a grid field)")
    lit_fn = compiled_lit_samples(model.occupancy, model.step, model.samples_per_ray, density)
    split = load_split(dataset, "train")
    generator = torch.Generator().manual_seed(seed)
    width, height = split.intrinsics.width, split.intrinsics.height
    made = []
    for _ in range(batches):
        views = torch.randint(0, len(split), (rays,), generator=generator)
        pixels = torch.randint(0, width * height, (rays,), generator=generator)
        origins, directions = camera_rays(split.intrinsics, split.poses[views], pixel_centres(width, pixels))
        near, far, _ = ray_box_intersection(origins, directions, model.occupancy.box_min, model.occupancy.box_max)
        offset = torch.rand((rays, 1), generator=generator)
        made.append((origins.contiguous(), directions.contiguous(), near.contiguous(), far.contiguous(), offset))
    return lit_fn, made


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--rays", type=int, default=2048)
    parser.add_argument("--batches", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    lit_fn, batches = training_batches(args.run, args.dataset, args.rays, args.batches)
    seconds, found = [], 0
    with torch.no_grad():
        for _ in range(args.repeats):
            for batch in batches:
                start = time.perf_counter()
                lit, _ = lit_fn(*batch)
                seconds.append(time.perf_counter() - start)
                found += len(lit)
    seconds.sort()
    print(f"{args.rays} rays a batch, {args.threads} threads: median {1000 * statistics.median(seconds):.2f} ms, "
          f"tenth percentile {1000 * seconds[len(seconds) // 10]:.2f} ms, fastest {1000 * seconds[0]:.2f} ms; "
          f"{found // len(seconds)} lit samples a batch")


if __name__ == "__main__":
    main()
