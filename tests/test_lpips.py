"""LPIPS: this project's implementation against the ``lpips`` package's own code, on AlexNet
weights the test builds itself (the real ImageNet weights cannot be downloaded here), and
LPIPS reported as unavailable, never faked, when weights are missing."""

from __future__ import annotations

import importlib.util
import json
import math
import os

import numpy as np
import pytest
import torch

from conftest import REPO_ROOT, run_python
from nerf_backend.metrics.lpips_metric import _CONVS, LpipsUnavailable, default_linear_path, load_lpips, lpips_distance


@pytest.fixture(scope="module")
def backbone_file(tmp_path_factory):
    """A torchvision-format AlexNet state dict with He-initialised random weights (so every
    layer's activations have a sensible scale), plus a classifier entry the loader must skip."""
    generator = torch.Generator().manual_seed(7)
    state = {}
    for index, cin, cout, kernel, _, _ in _CONVS:
        fan_in = cin * kernel * kernel
        state[f"features.{index}.weight"] = torch.randn(cout, cin, kernel, kernel, generator=generator) * math.sqrt(2 / fan_in)
        state[f"features.{index}.bias"] = torch.randn(cout, generator=generator) * 0.01
    state["classifier.6.bias"] = torch.zeros(1000)
    path = tmp_path_factory.mktemp("lpips") / "alexnet-test.pth"
    torch.save(state, path)
    return path


def _image_pairs() -> dict[str, np.ndarray]:
    """Pairs at 64×64 and 96×80: a photograph against itself blurred, shifted and noised, and noise."""
    from skimage import data, filters, transform

    photo = transform.resize(data.astronaut(), (96, 80), anti_aliasing=True).astype(np.float32)
    rng = np.random.default_rng(0)
    a = [photo, photo, photo, photo]
    b = [filters.gaussian(photo, sigma=1.5, channel_axis=-1).astype(np.float32),
         np.roll(photo, 3, axis=1),
         np.clip(photo + rng.normal(0, 0.05, photo.shape), 0, 1).astype(np.float32),
         photo]
    return {"a": np.stack(a), "b": np.stack(b)}


def test_the_lpips_package_is_installed_for_its_linear_weights():
    assert importlib.util.find_spec("lpips") is not None, "make setup installs lpips (without dependencies)"
    assert default_linear_path().is_file()


def test_matches_the_lpips_package_on_the_same_weights(backbone_file, tmp_path):
    pairs = _image_pairs()
    np.savez(tmp_path / "pairs.npz", **pairs)
    env = {**os.environ, "LPIPS_TEST_BACKBONE": str(backbone_file),
           "PYTHONPATH": str(REPO_ROOT / "tests" / "reference_torchvision")}
    run_python(str(REPO_ROOT / "tests" / "reference_lpips.py"), str(tmp_path / "pairs.npz"),
               str(tmp_path / "reference.npy"), env=env)
    reference = np.load(tmp_path / "reference.npy")
    metric = load_lpips(backbone_file)
    ours = np.array([lpips_distance(metric, a, b) for a, b in zip(pairs["a"], pairs["b"])])
    print("reference", reference, "ours", ours)
    assert np.abs(ours - reference).max() < 1e-4
    assert ours[3] == pytest.approx(0.0, abs=1e-7)  # identical images
    assert min(ours[:3]) > 1e-3  # real distortions give real distances


def test_is_symmetric_and_grows_with_the_distortion(backbone_file):
    metric = load_lpips(backbone_file)
    photo = _image_pairs()["a"][0]
    rng = np.random.default_rng(1)
    noisy = [np.clip(photo + rng.normal(0, s, photo.shape), 0, 1) for s in (0.02, 0.08, 0.2)]
    distances = [lpips_distance(metric, photo, n) for n in noisy]
    assert distances == sorted(distances)
    assert lpips_distance(metric, noisy[1], photo) == pytest.approx(distances[1], abs=1e-6)


def test_missing_backbone_is_reported_with_the_way_to_enable_it(tmp_path):
    with pytest.raises(LpipsUnavailable) as error:
        load_lpips(tmp_path / "no-such-alexnet.pth")
    assert "no-such-alexnet.pth" in str(error.value) and "--lpips-weights" in str(error.value)


def test_eval_reports_lpips_null_with_reason_or_a_real_number(trained_run, backbone_file):
    # Without weights (this machine has none): null, and why.
    run_python("-m", "nerf_backend", "eval", str(trained_run), "--no-progress",
               "--lpips-weights", str(backbone_file.parent / "absent.pth"))
    metrics = json.loads((trained_run / "metrics.json").read_text())
    assert metrics["lpips"] is None and all(v["lpips"] is None for v in metrics["per_view"])
    assert "absent.pth" in metrics["lpips_unavailable"]
    # With the test's weights file: a number per view, equal to the metric computed directly.
    result = run_python("-m", "nerf_backend", "eval", str(trained_run), "--no-progress",
                        "--lpips-weights", str(backbone_file))
    metrics = json.loads((trained_run / "metrics.json").read_text())
    assert metrics["lpips_unavailable"] is None and "LPIPS" in result.stdout
    from nerf_backend.data.dataset import load_split
    from nerf_backend.evaluation.evaluate import read_rgb

    split = load_split(metrics["dataset"], "test")
    metric = load_lpips(backbone_file)
    for index, view in enumerate(metrics["per_view"]):
        rendered = read_rgb(trained_run / "renders" / "test" / f"{view['view']}.png")
        assert view["lpips"] == pytest.approx(lpips_distance(metric, rendered, split.rgb_on_white(index).numpy()), abs=1e-6)
    assert metrics["lpips"] == pytest.approx(np.mean([v["lpips"] for v in metrics["per_view"]]))
