"""PSNR and SSIM against scikit-image's on the same images."""

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from nerf_backend.metrics.image_metrics import psnr, ssim


def _image_pair(seed, shape=(64, 48, 3)):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:shape[0], 0:shape[1]]
    base = np.stack([0.5 + 0.4 * np.sin(x / 5.0 + c) * np.cos(y / 7.0) for c in range(3)], axis=-1)
    noisy = np.clip(base + rng.normal(0, 0.05, shape), 0, 1)
    return base, noisy


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_psnr_and_ssim_match_scikit_image(seed):
    reference, image = _image_pair(seed)
    assert psnr(image, reference) == pytest.approx(peak_signal_noise_ratio(reference, image, data_range=1.0), abs=1e-6)
    expected = structural_similarity(reference, image, gaussian_weights=True, sigma=1.5,
                                     use_sample_covariance=False, data_range=1.0, channel_axis=-1)
    assert abs(ssim(image, reference) - expected) < 1e-4


def test_identical_images():
    reference, _ = _image_pair(3)
    assert psnr(reference, reference) == float("inf")
    assert ssim(reference, reference) == pytest.approx(1.0, abs=1e-12)
