"""Rendering memory stays bounded at any resolution (chunks of rays, not whole images)."""

from __future__ import annotations

import json
import textwrap

import pytest

from conftest import run_python

RENDER_LARGE = textwrap.dedent("""
    import json, resource, sys, torch
    from nerf_backend.data.dataset import load_split
    from nerf_backend.evaluation.inference import load_trained_model
    from nerf_backend.evaluation.render_views import render_image
    from nerf_backend.data.run_folder import RunFolder
    run, dataset, size = sys.argv[1], sys.argv[2], int(sys.argv[3])
    model, bounds, _ = load_trained_model(RunFolder(run), torch.device("cpu"))
    view = load_split(dataset, "test")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    image = render_image(model, view.intrinsics.scaled(size / view.intrinsics.width), view.poses[0], bounds)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"shape": list(image.rgb.shape), "finite": bool(torch.isfinite(torch.from_numpy(image.rgb)).all()),
                      "before_mb": before, "peak_mb": peak}))
""")


@pytest.mark.slow
@pytest.mark.parametrize("size", [1024, 4096])
def test_large_renders_keep_memory_bounded(tiny_demo_dataset, tmp_path, size):
    run = tmp_path / "run"
    run_python("-m", "nerf_backend", "train", str(tiny_demo_dataset), "--preset", "fast", "--out", str(run),
               "--iters", "50", "--no-progress")
    result = json.loads(run_python("-c", RENDER_LARGE, str(run), str(tiny_demo_dataset), str(size),
                                   timeout=3600).stdout.splitlines()[-1])
    assert result["shape"] == [size, size, 3] and result["finite"]
    # The output arrays are 5 floats a pixel (rgb, depth, opacity): 20 bytes × size². Beyond
    # them, rendering may add at most 600 MB (one chunk's samples), whatever the size.
    outputs_mb = 20 * size * size / 2**20
    print(f"{size}×{size}: peak {result['peak_mb']:.0f} MB, {result['before_mb']:.0f} MB before rendering")
    assert result["peak_mb"] - result["before_mb"] < outputs_mb + 600
