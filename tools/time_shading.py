"""Deferred colour's network alone, in training and at rendering: a trained run's colour network
through the compiled passes (``kernels/colour_network.h``) and through PyTorch's own modules
(oneDNN's products), against the machine's matrix-product rate measured in the same round:
issue 59's "the colour network's products near the FMA peak, at training and at rendering, both
measured, the faster kept".

    python tools/time_shading.py RUN [--rays 940,2000,15000] [--threads 2] [--rounds 5] [--calls 200]

For each size, ``rays`` of twice as many rays are shaded (every other one, as a step's shaded
rays lie among its unshaded ones) from random features and directions. Timed, each the median
of the last four fifths of ``calls``:
- training, compiled pass: its two compiled calls alone (forward, then backward: the gathers,
  the layers, the sigmoid, the weighting and the scatters);
- training, node: ``volume_rendering.shade_rays`` forward and backward through autograd, the
  step's whole cost of the shading (the node's tensors, the weights' preparation, the
  gradients' accumulation);
- training, PyTorch: the same through PyTorch's modules (the path without a compiler);
- rendering, compiled and PyTorch: ``shade_rays`` without gradients.
Each is printed as GFLOP/s and as a share of the product rate (a 2 048³ float32 product on the
same threads, measured before the round), for each round; then each share's median and range
over the rounds (this VM's speed moves by up to 1.8× within a minute: a share is only read
against the rate measured beside it). A ray's FLOPs are the network's (the basis over the
features, then three layers), three times that forward and backward."""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from nerf_backend.bench.hardware import measure_hardware
from nerf_backend.core.allocator import keep_freed_memory
from nerf_backend.data.run_folder import RunFolder
from nerf_backend.evaluation.inference import load_trained_model
from nerf_backend.field_components.compiled_colour import COMPILED_WIDTH, compiled_shade, compiled_shade_training
from nerf_backend.model_components.volume_rendering import MIN_SHADED_WEIGHT, shade_rays


def network_flops(field) -> int:
    """A ray's forward FLOPs: the basis over the features, then three layers of the network."""
    appearance, features = field.appearance_basis.weight.shape
    encoding = field.direction_encoding.out_dims
    width = COMPILED_WIDTH
    return 2 * (features * appearance + (appearance + encoding) * width + width * width + width * 3)


def pytorch_shading(field):
    """The same network through PyTorch's modules (the path without a compiler)."""
    return lambda mean, directions: field.colour_from_grid(mean, field.direction_inputs(directions))


def composited_rays(field, shaded: int, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """What a step's compositing gives ``shade_rays``: 2·``shaded`` rays, every other one with
    coloured weight (the rest none), their features, weights and directions."""
    generator = torch.Generator().manual_seed(seed)
    rays = 2 * shaded
    accumulated = torch.randn(rays, field.appearance_grid.out_dims, generator=generator)
    coloured_weight = (0.5 + 0.5 * torch.rand(rays, generator=generator)) * (torch.arange(rays) % 2 == 0)
    weight = coloured_weight + 0.1 * torch.rand(rays, generator=generator)
    directions = torch.nn.functional.normalize(torch.randn(rays, 3, generator=generator), dim=1)
    return accumulated, coloured_weight, weight, directions


def median_seconds(run, calls: int) -> float:
    """The median of ``run()``'s last four fifths of ``calls`` (the first warm the caches and the
    allocator)."""
    seconds = []
    for _ in range(calls):
        start = time.perf_counter()
        run()
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds[calls // 5:])


def compiled_pass(field, composited) -> callable:
    """The training pass's two compiled calls alone (``CompiledShadeTraining.forward_pass`` and
    ``backward_pass``, their buffers included), without autograd."""
    shader = compiled_shade_training(field)
    accumulated, coloured_weight, weight, directions = composited
    shaded = (coloured_weight > MIN_SHADED_WEIGHT).nonzero().squeeze(1)
    first, second, third = field.colour_mlp[0], field.colour_mlp[2], field.colour_mlp[4]
    network, kept = shader.network(field.appearance_basis.weight, first.weight, first.bias, second.weight,
                                   second.bias, third.weight, third.bias)
    grad_rgb = torch.randn(accumulated.shape[0], 3)

    def run() -> None:
        _, rows = shader.forward_pass(network, accumulated, coloured_weight, weight, directions, shaded)
        shader.backward_pass(network, coloured_weight, weight, shaded, rows, grad_rgb, accumulated.shape[0])
    run.kept = kept  # the prepared weights live as long as the pass
    return run


def training_node(field, shade, composited) -> callable:
    """``shade_rays`` forward and backward through autograd, as a step runs it."""
    upstream = torch.randn(composited[0].shape[0], 3)

    def run() -> None:
        field.zero_grad(set_to_none=True)
        inputs = [t.clone().requires_grad_(True) for t in composited[:3]]
        shade_rays(*inputs, composited[3], shade).backward(upstream)
    return run


def rendering(shade, composited) -> callable:
    def run() -> None:
        with torch.no_grad():
            shade_rays(*composited, shade)
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--rays", default="940,2000,15000", help="shaded rays a call (default: lego's a step, "
                        "2 000, and a rendered chunk's)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--calls", type=int, default=200)
    args = parser.parse_args()
    keep_freed_memory()  # as the commands do: freed blocks kept, not faulted in again each call
    torch.set_num_threads(args.threads)
    field = load_trained_model(RunFolder(args.run), torch.device("cpu"))[0].field.train()
    if compiled_shade_training(field) is None:
        raise SystemExit(f"{args.run}: its shading has no compiled pass here (no C compiler, or not deferred colour)")
    flops = network_flops(field)
    print(f"{args.run}: {flops} FLOPs a ray forward, {args.threads} threads")
    shares: dict[tuple[int, str], list[float]] = {}
    for round_number in range(1, args.rounds + 1):
        for rays in (int(r) for r in args.rays.split(",")):
            composited = composited_rays(field, rays)
            field.train()
            variants = [("training, compiled pass", 3, compiled_pass(field, composited)),
                        ("training, node", 3, training_node(field, compiled_shade_training(field), composited)),
                        ("training, PyTorch", 3, training_node(field, pytorch_shading(field), composited))]
            field.eval()
            variants += [("rendering, compiled", 1, rendering(compiled_shade(field), composited)),
                         ("rendering, PyTorch", 1, rendering(pytorch_shading(field), composited))]
            rate = measure_hardware(torch.device("cpu"), table_bytes=2**24)["gflops"]
            for name, passes, run in variants:
                field.train(name.startswith("training"))
                achieved = passes * flops * rays / median_seconds(run, args.calls) / 1e9
                shares.setdefault((rays, name), []).append(achieved / rate)
                print(f"round {round_number}, {rays:6d} rays, {name:24s}: {achieved:6.1f} GFLOP/s, "
                      f"{achieved / rate:4.0%} of the product rate ({rate:.0f} GFLOP/s)", flush=True)
    print("\nshare of the product rate, median (range) over the rounds:")
    for (rays, name), values in shares.items():
        print(f"{rays:6d} rays, {name:24s}: {statistics.median(values):4.0%} ({min(values):.0%}-{max(values):.0%})")


if __name__ == "__main__":
    main()
