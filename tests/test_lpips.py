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


@pytest.fixture
def served(tmp_path):
    """A local HTTP server over a folder: the download path is tested against it, offline."""
    import functools
    import http.server
    import threading

    folder = tmp_path / "served"
    folder.mkdir()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(folder))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield folder, f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def _named_by_its_hash(source, folder, stem="alexnet-test"):
    """A copy of ``source`` named as torchvision names its weights: STEM-<first 8 of SHA-256>.pth."""
    import hashlib

    data = source.read_bytes()
    name = f"{stem}-{hashlib.sha256(data).hexdigest()[:8]}.pth"
    (folder / name).write_bytes(data)
    return name


def test_the_backbone_is_downloaded_once_and_checked_against_its_hash(served, backbone_file, tmp_path):
    from nerf_backend.metrics.lpips_metric import fetch_backbone

    folder, base = served
    name = _named_by_its_hash(backbone_file, folder)
    cache = tmp_path / "hub" / "checkpoints"
    path = fetch_backbone(f"{base}/{name}", cache / name, progress=False)
    assert path == cache / name and path.read_bytes() == backbone_file.read_bytes()
    (folder / name).unlink()  # already there: not fetched again
    assert fetch_backbone(f"{base}/{name}", cache / name, progress=False) == path


def test_a_download_whose_hash_does_not_match_is_refused_and_nothing_kept(served, backbone_file, tmp_path):
    from nerf_backend.metrics.lpips_metric import fetch_backbone

    folder, base = served
    (folder / "alexnet-test-00000000.pth").write_bytes(backbone_file.read_bytes())
    cache = tmp_path / "hub" / "checkpoints"
    with pytest.raises(LpipsUnavailable, match="refused, its SHA-256 does not start with 00000000"):
        fetch_backbone(f"{base}/alexnet-test-00000000.pth", cache / "alexnet-test-00000000.pth", progress=False)
    assert list(cache.iterdir()) == []  # no partial or unchecked file left behind


def test_offline_the_download_fails_with_the_reason(tmp_path):
    from nerf_backend.metrics.lpips_metric import fetch_backbone

    with pytest.raises(LpipsUnavailable, match="could not download alexnet-owt-7be5be79.pth from 127.0.0.1:9 into"):
        fetch_backbone("http://127.0.0.1:9/alexnet-owt-7be5be79.pth",  # the discard port: nothing listens
                       tmp_path / "alexnet-owt-7be5be79.pth", progress=False)
    assert not (tmp_path / "alexnet-owt-7be5be79.pth").exists()


def test_a_first_eval_downloads_the_backbone_and_scores_lpips(served, backbone_file, trained_run, tmp_path, monkeypatch):
    """`eval RUN` with no weights anywhere: the backbone comes from the (local) published URL into
    torch hub's cache, and every view gets a real LPIPS number."""
    from nerf_backend import cli
    from nerf_backend.metrics import lpips_metric

    folder, base = served
    name = _named_by_its_hash(backbone_file, folder)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(lpips_metric, "BACKBONE_FILE", name)
    monkeypatch.setattr(lpips_metric, "BACKBONE_URL", f"{base}/{name}")
    monkeypatch.setattr(lpips_metric, "_fetch_failure", None)
    assert cli.main(["eval", str(trained_run), "--no-progress"]) == 0
    assert (tmp_path / "torch" / "hub" / "checkpoints" / name).read_bytes() == backbone_file.read_bytes()
    metrics = json.loads((trained_run / "metrics.json").read_text())
    assert metrics["lpips_unavailable"] is None and metrics["lpips"] > 0
    assert all(view["lpips"] is not None for view in metrics["per_view"])
