"""Image quality metrics as the NeRF literature computes them, on RGB images in [0, 1].

SSIM follows Wang et al. 2004 with an 11×11 Gaussian window (σ = 1.5), population
statistics and the mean over the window's valid region — the same numbers as
``skimage.metrics.structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)``.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor


def mse_to_psnr(mse: float) -> float:
    """PSNR in dB for data range 1; infinite for identical images."""
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


def psnr(image: np.ndarray | Tensor, reference: np.ndarray | Tensor) -> float:
    a = torch.as_tensor(np.asarray(image, dtype=np.float64))
    b = torch.as_tensor(np.asarray(reference, dtype=np.float64))
    return mse_to_psnr(float(((a - b) ** 2).mean()))


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(image: np.ndarray | Tensor, reference: np.ndarray | Tensor, window: int = 11, sigma: float = 1.5) -> float:
    """Mean SSIM of two ``H×W×3`` images in [0, 1] (float64 throughout)."""
    a = torch.as_tensor(np.asarray(image, dtype=np.float64)).permute(2, 0, 1)[None]
    b = torch.as_tensor(np.asarray(reference, dtype=np.float64)).permute(2, 0, 1)[None]
    channels = a.shape[1]
    if min(a.shape[-2:]) < window:
        raise ValueError(f"SSIM needs images of at least {window}×{window} pixels, got {tuple(a.shape[-2:])}")
    g = _gaussian_window(window, sigma)
    kernel_x = g.view(1, 1, 1, -1).repeat(channels, 1, 1, 1)
    kernel_y = g.view(1, 1, -1, 1).repeat(channels, 1, 1, 1)

    def blur(x: Tensor) -> Tensor:  # separable, 'valid' region only
        return F.conv2d(F.conv2d(x, kernel_x, groups=channels), kernel_y, groups=channels)

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return float(ssim_map.mean())
