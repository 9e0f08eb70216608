"""Training's deferred shading alone, forward and backward: a trained run's colour network
through the compiled pass (``CompiledShadeTraining``, ``kernels/colour_network.h``) and through
PyTorch's own modules (oneDNN's products), on random mean features and directions, against the
machine's measured matrix-product rate: issue 59's "the colour network's products near the FMA
peak, both measured, the faster kept".

    python tools/time_training_shading.py RUN [--rays 1000,2000,8000] [--threads 1,2] [--calls 200]

Prints each size's median seconds (of the last four fifths of the calls) and its GFLOP/s: the
network's FLOPs a ray (the basis, three layers) three times over, forward and backward."""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from nerf_backend.bench.hardware import measure_hardware
from nerf_backend.data.run_folder import RunFolder
from nerf_backend.evaluation.inference import load_trained_model
from nerf_backend.field_components.compiled_colour import COMPILED_WIDTH, compiled_shade_training


def network_flops(field) -> int:
    """A ray's forward FLOPs: the basis over the features, then three layers of the network."""
    appearance, features = field.appearance_basis.weight.shape
    encoding = field.direction_encoding.out_dims
    width = COMPILED_WIDTH
    return 2 * (features * appearance + (appearance + encoding) * width + width * width + width * 3)


def pytorch_shading(field):
    """The same network through PyTorch's modules (the path without a compiler)."""
    return lambda mean, directions: field.colour_from_grid(mean, field.direction_inputs(directions))


def median_seconds(shade, field, mean: torch.Tensor, directions: torch.Tensor, calls: int) -> float:
    """Forward and backward of ``shade`` on ``mean``, ``calls`` times: the median of the last
    four fifths (the first warm the caches and the allocator)."""
    seconds = []
    for _ in range(calls):
        field.zero_grad(set_to_none=True)
        features = mean.clone().requires_grad_(True)
        start = time.perf_counter()
        colour = shade(features, directions)
        colour.backward(torch.ones_like(colour))
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds[calls // 5:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--rays", default="1000,2000,8000")
    parser.add_argument("--threads", default="1,2")
    parser.add_argument("--calls", type=int, default=200)
    args = parser.parse_args()
    field = load_trained_model(RunFolder(args.run), torch.device("cpu"))[0].field.train()
    compiled = compiled_shade_training(field)
    if compiled is None:
        raise SystemExit(f"{args.run}: its shading has no compiled pass here (no C compiler, or not deferred colour)")
    flops = network_flops(field)
    rate = measure_hardware(torch.device("cpu"), table_bytes=2**24)["gflops"]
    print(f"{flops} FLOPs a ray forward; the matrix-product rate {rate:.0f} GFLOP/s on {torch.get_num_threads()} "
          f"threads")
    for rays in (int(r) for r in args.rays.split(",")):
        generator = torch.Generator().manual_seed(0)
        mean = torch.randn(rays, field.appearance_grid.out_dims, generator=generator)
        directions = torch.nn.functional.normalize(torch.randn(rays, 3, generator=generator), dim=1)
        for threads in (int(t) for t in args.threads.split(",")):
            torch.set_num_threads(threads)
            for name, shade in (("compiled", compiled), ("pytorch", pytorch_shading(field))):
                seconds = median_seconds(shade, field, mean, directions, args.calls)
                achieved = 3 * flops * rays / seconds / 1e9
                print(f"{rays:6d} rays, {threads} threads, {name:8s}: {1000 * seconds:.3f} ms, {achieved:.1f} GFLOP/s "
                      f"({achieved / rate:.0%} of the product rate)")


if __name__ == "__main__":
    main()
