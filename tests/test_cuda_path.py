"""The CUDA path against the CPU's: the same grids, the same model, the same rays must give the
same numbers on both, and a training step must not stop to wait for the GPU where it need not.

CI has no GPU, so these skip there; on a machine with CUDA, `pytest tests/test_cuda_path.py`.
The CPU reads the factorised grids through its own kernel (channel rows, `embedding_bag`) and
CUDA through `grid_sample`, so these also check that the two kernels agree across devices."""

from __future__ import annotations

import warnings

import pytest
import torch
from test_fast_model import BOX, _solid_grid_model

from nerf_backend.core.cameras import ray_box_intersection
from nerf_backend.field_components.grid_encodings import VectorMatrixGrid

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="torch sees no CUDA device here")

CUDA = torch.device("cuda")


def _rays(count: int, seed: int) -> tuple[torch.Tensor, ...]:
    generator = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1) * 4.0
    targets = torch.rand(count, 3, generator=generator) * 2.0 - 1.0
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    near, far, _ = ray_box_intersection(origins, directions, torch.tensor(BOX.box_min), torch.tensor(BOX.box_max))
    return origins, directions, near, far


def test_cuda_grid_sample_reads_the_grid_as_the_cpu_kernel_does():
    torch.manual_seed(5)
    grid = VectorMatrixGrid(channels=6, vertices=(33, 29, 17))
    points = torch.rand(20_000, 3) * 2.4 - 1.2
    upstream = torch.randn(20_000, 18)
    results = []
    for device in ("cpu", CUDA):
        moved = VectorMatrixGrid(channels=6, vertices=(33, 29, 17)).to(device)
        moved.load_state_dict(grid.state_dict())
        features = moved(points.to(device))
        (features * upstream.to(device)).sum().backward()
        results.append((features.detach().cpu(), [p.grad.cpu() for p in moved.parameters()]))
    (cpu_features, cpu_grads), (cuda_features, cuda_grads) = results
    # float32 on both sides, different summation order: a few ulps of the features' scale.
    assert torch.allclose(cuda_features, cpu_features, atol=1e-5, rtol=1e-5)
    for got, expected in zip(cuda_grads, cpu_grads):
        # A gradient sums thousands of samples a vertex, in another order on each device.
        assert torch.allclose(got, expected, atol=1e-3, rtol=1e-4)


def test_the_model_renders_the_same_image_on_cuda_as_on_the_cpu():
    """Both the training march (with gradients) and the inference path (occupied spans, early
    stop, the dense density volume) give the CPU's colour, opacity and depth."""
    model = _solid_grid_model().eval()
    rays = _rays(4000, seed=4)
    on_cpu = {}
    for device in ("cpu", CUDA):
        moved = model.to(device)
        moved_rays = [r.to(device) for r in rays]
        with torch.enable_grad():
            full = moved(*moved_rays)[0]
        with torch.no_grad():
            fast = moved(*moved_rays)[0]
        outputs = {"train": full, "render": fast}
        for path, result in outputs.items():
            values = (result.rgb.detach().cpu(), result.opacity.detach().cpu(), result.depth.detach().cpu())
            if device == "cpu":
                on_cpu[path] = values
                continue
            (rgb, opacity, depth), (cpu_rgb, cpu_opacity, cpu_depth) = values, on_cpu[path]
            # float32 with other kernels: a step's alpha may fall either side of a threshold,
            # so a rare ray moves by up to the early stop's bound; the mean stays at rounding.
            assert (rgb - cpu_rgb).abs().max() < 2e-3, path
            assert (rgb - cpu_rgb).abs().mean() < 2e-5, path
            assert (opacity - cpu_opacity).abs().max() < 2e-3, path
            assert (depth - cpu_depth).abs().max() < 1e-2, path


def test_a_training_step_gives_the_cpu_gradients_and_waits_for_the_gpu_a_bounded_number_of_times():
    """The loss's gradient through march, fields and compositing matches the CPU's (without the
    random offset of training, so both devices march the same steps). Packing samples per ray
    needs their count on the host (three packings: samples with a length, in occupied cells,
    still lit), so a step waits for the GPU a few times; the waits are counted, each printed
    with the line that caused it, and bounded by the count measured on an H200 (12, torch
    2.11), so that a new wait fails here. Nine of those 12 were then traced, by reading, to the
    grids' list index (``x[:, [b, a]]``, 3 planes × 3 grid reads a step), since replaced; the
    bound stays at the measured count until a GPU measures the new one (3 expected)."""
    model = _solid_grid_model().eval()
    rays = _rays(2048, seed=7)
    target = torch.rand(2048, 3, generator=torch.Generator().manual_seed(8))
    gradients = []
    for device in ("cpu", CUDA):
        moved = model.to(device)
        moved.zero_grad()
        with torch.enable_grad():
            rgb = moved(*[r.to(device) for r in rays])[-1].rgb
            ((rgb - target.to(device)) ** 2).mean().backward()
        gradients.append([p.grad.detach().cpu().clone() for p in moved.parameters() if p.grad is not None])
    cpu_gradients, cuda_gradients = gradients
    assert len(cuda_gradients) == len(cpu_gradients) > 0
    for got, expected in zip(cuda_gradients, cpu_gradients):
        scale = expected.abs().max().clamp_min(1e-6)
        assert (got - expected).abs().max() / scale < 5e-3

    model.train()
    cuda_rays, cuda_target = [r.to(CUDA) for r in rays], target.to(CUDA)
    for record in (False, True):  # the first step loads kernels, which synchronises
        model.zero_grad()
        torch.cuda.synchronize()
        if record:
            torch.cuda.set_sync_debug_mode("warn")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                rgb = model(*cuda_rays)[-1].rgb
                ((rgb - cuda_target) ** 2).mean().backward()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    waits = [f"{w.filename}:{w.lineno}" for w in caught if "synchroniz" in str(w.message).lower()]
    print(f"synchronisations in one training forward+backward on CUDA: {len(waits)}")
    for place in sorted(set(waits)):
        print("  ", waits.count(place), place)
    assert len(waits) <= 12, waits


def test_cuda_reads_the_sparse_grid_as_the_cpu_kernel_does():
    """The Plenoxels grid: PyTorch's gathers on CUDA against the CPU's compiled kernel (or its
    gathers where no compiler is found), features and gradients, with pruned vertices."""
    from nerf_backend.field_components.sparse_grid import SparseVoxelGrid

    generator = torch.Generator().manual_seed(6)
    vertices = (17, 13, 11)
    keep = torch.rand(vertices, generator=generator) < 0.7
    points = torch.rand(20_000, 3, generator=generator) * 2.4 - 1.2
    upstream = torch.randn(20_000, 28, generator=generator)
    values = torch.randn(int(keep.sum()), 32, generator=generator)
    results = []
    for device in ("cpu", CUDA):
        grid = SparseVoxelGrid(28, vertices, keep).to(device)
        with torch.no_grad():
            grid.values.copy_(values.to(device))
        features = grid(points.to(device))
        (features * upstream.to(device)).sum().backward()
        results.append((features.detach().cpu(), grid.values.grad.cpu()))
    (cpu_features, cpu_grad), (cuda_features, cuda_grad) = results
    assert torch.allclose(cuda_features, cpu_features, atol=1e-5, rtol=1e-5)
    assert torch.allclose(cuda_grad, cpu_grad, atol=1e-3, rtol=1e-4)
