"""PSNR against scikit-image's; SSIM on analytic cases, and the compiled SSIM (kernels/ssim.c)
against scikit-image's, which is also its fallback."""

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio

from nerf_backend.metrics import image_metrics
from nerf_backend.metrics.image_metrics import psnr, reference_ssim, ssim


def _image_pair(seed, shape=(64, 48, 3)):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:shape[0], 0:shape[1]]
    base = np.stack([0.5 + 0.4 * np.sin(x / 5.0 + c) * np.cos(y / 7.0) for c in range(shape[2])], axis=-1)
    noisy = np.clip(base + rng.normal(0, 0.05, shape), 0, 1)
    return base, noisy


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_psnr_matches_scikit_image(seed):
    reference, image = _image_pair(seed)
    assert psnr(image, reference) == pytest.approx(peak_signal_noise_ratio(reference, image, data_range=1.0), abs=1e-6)


@pytest.mark.parametrize("a, b", [(0.3, 0.6), (0.0, 1.0), (0.5, 0.5), (0.9, 0.85)])
def test_ssim_of_flat_images_is_the_luminance_term(a, b):
    """Two flat images have no variance or covariance, so SSIM is its luminance term alone,
    (2ab + C1) / (a² + b² + C1) with C1 = 0.01², at every pixel of the window's valid region."""
    image, reference = np.full((40, 30, 3), a), np.full((40, 30, 3), b)
    c1 = 0.01**2
    assert ssim(image, reference) == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), abs=1e-12)


def test_ssim_falls_with_the_noise():
    """More noise, less structure kept: SSIM orders noisy copies of an image by their noise."""
    reference, _ = _image_pair(4, shape=(64, 64, 3))
    rng = np.random.default_rng(4)
    noise = rng.normal(0, 1, reference.shape)
    scores = [ssim(np.clip(reference + level * noise, 0, 1), reference) for level in (0.01, 0.03, 0.1, 0.3)]
    assert scores == sorted(scores, reverse=True) and scores[0] > 0.95 and scores[-1] < 0.5


def test_ssim_refuses_an_image_smaller_than_its_window():
    with pytest.raises(ValueError, match="at least 11×11"):
        ssim(np.zeros((10, 40, 3)), np.zeros((10, 40, 3)))


def test_identical_images():
    reference, _ = _image_pair(3)
    assert psnr(reference, reference) == float("inf")
    assert ssim(reference, reference) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("shape", [(11, 11, 3), (12, 30, 1), (37, 53, 3), (64, 48, 4), (200, 130, 3)])
def test_the_compiled_ssim_is_scikit_images(shape):
    """The smallest image (one valid pixel), one channel, odd sizes, more channels and rows than
    the kernel's ring holds: equal to scikit-image's float64 SSIM within 1e-12. A window off by
    a pixel, a moment dropped or the border counted shifts these by 1e-4 or more."""
    assert image_metrics.kernel_or_note("ssim", "")[0] is not None  # make setup's machines have gcc
    for seed in range(3):
        reference, image = _image_pair(seed, shape)
        rng = np.random.default_rng(seed)
        image[rng.random(shape[:2]) < 0.05] = 1.0  # saturated specks: large local variances
        assert ssim(image, reference) == pytest.approx(reference_ssim(image, reference), abs=1e-12)


def test_without_a_compiler_ssim_is_scikit_images(monkeypatch):
    reference, image = _image_pair(5)
    monkeypatch.setattr(image_metrics, "kernel_or_note", lambda name, instead: (None, "no C compiler"))
    assert ssim(image, reference) == reference_ssim(image, reference)


def test_ssim_refuses_images_of_different_sizes():
    with pytest.raises(ValueError, match="one size"):
        ssim(np.zeros((20, 20, 3)), np.zeros((20, 21, 3)))
