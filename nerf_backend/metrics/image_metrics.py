"""Image quality metrics as the NeRF literature computes them, on RGB images in [0, 1].

SSIM follows Wang et al. 2004 with an 11×11 Gaussian window (σ = 1.5), population
statistics and the mean over the window's valid region: scikit-image's
``structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
data_range=1, channel_axis=-1)``, as the NeRF papers' evaluation code computes it.
"""

from __future__ import annotations

import ctypes
import functools
import math

import numpy as np
import torch
from torch import Tensor

from ..kernels.build import kernel_or_note


def mse_to_psnr(mse: float) -> float:
    """PSNR in dB for data range 1; infinite for identical images."""
    return math.inf if mse <= 0 else -10.0 * math.log10(mse)


def psnr(image: np.ndarray | Tensor, reference: np.ndarray | Tensor) -> float:
    """PSNR for data range 1, the squared error summed in float64 (as one dot product: through
    PyTorch's elementwise float64 ops an 800×800 view took 15 ms, here 4)."""
    difference = (_float64(image) - _float64(reference)).ravel()
    return mse_to_psnr(float(difference @ difference) / difference.size)


def _float64(image: np.ndarray | Tensor) -> np.ndarray:
    if isinstance(image, Tensor):
        image = image.detach().cpu().numpy()
    return np.asarray(image, dtype=np.float64)


# SSIM's window: 11×11 pixels, Gaussian weights of σ = 1.5 (scikit-image's filter radius, 3.5 σ).
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5


# scikit-image's constants: K1 = 0.01, K2 = 0.03 of the data range (1).
SSIM_C1, SSIM_C2 = 0.01 ** 2, 0.03 ** 2


def ssim(image: np.ndarray | Tensor, reference: np.ndarray | Tensor) -> float:
    """Mean SSIM of two ``H×W×C`` images in [0, 1], in float64: the compiled kernel
    (``kernels/ssim.c``: 0.05-0.08 s an 800×800 RGB pair on one core, its conversion to float64
    included) where a C compiler is found, else scikit-image's ``structural_similarity``
    (``reference_ssim``: 0.3-0.7 s, in turn with it), the same number to 1e-12
    (tests/test_metrics.py)."""
    a, b = _float64_images(image, reference)
    library = _ssim_kernel()
    if library is None:
        return reference_ssim(a, b)
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    weights = _ssim_weights()
    value = library.ssim_mean(
        a.ctypes.data_as(ctypes.c_void_p), b.ctypes.data_as(ctypes.c_void_p),
        ctypes.c_int64(a.shape[0]), ctypes.c_int64(a.shape[1]), ctypes.c_int64(a.shape[2]),
        weights.ctypes.data_as(ctypes.c_void_p), ctypes.c_int64(len(weights) // 2), ctypes.c_double(SSIM_C1),
        ctypes.c_double(SSIM_C2))
    if value < 0:  # the kernel could not take it (out of memory): scikit-image computes it
        return reference_ssim(a, b)
    return float(value)


def reference_ssim(image: np.ndarray | Tensor, reference: np.ndarray | Tensor) -> float:
    """``ssim`` as scikit-image computes it (the fallback, and the tests' reference)."""
    # Imported here: scikit-image's metrics bring scipy.ndimage, 0.3 s, which training never needs.
    from skimage.metrics import structural_similarity

    a, b = _float64_images(image, reference)
    return float(structural_similarity(a, b, gaussian_weights=True, sigma=SSIM_SIGMA, use_sample_covariance=False,
                                       data_range=1.0, channel_axis=-1))


def _float64_images(image: np.ndarray | Tensor, reference: np.ndarray | Tensor) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.asarray(image, dtype=np.float64), np.asarray(reference, dtype=np.float64)
    if a.ndim != 3 or a.shape != b.shape:
        raise ValueError(f"SSIM needs two H×W×C images of one size, got {a.shape} and {b.shape}")
    if min(a.shape[:2]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}×{SSIM_WINDOW} pixels, got {a.shape[:2]}")
    return a, b


def _ssim_kernel() -> ctypes.CDLL | None:
    """The built ``kernels/ssim.c`` (its result type declared), or None: no C compiler, said
    once on stderr."""
    library, _ = kernel_or_note("ssim", "SSIM through scikit-image")
    if library is not None:
        library.ssim_mean.restype = ctypes.c_double
    return library


@functools.cache
def _ssim_weights() -> np.ndarray:
    """scipy's Gaussian of σ = SSIM_SIGMA over SSIM_WINDOW taps (its radius: 3.5 σ, rounded),
    normalised to sum 1, as scikit-image filters with."""
    radius = SSIM_WINDOW // 2
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    weights = np.exp(-0.5 / SSIM_SIGMA ** 2 * x ** 2)
    return weights / weights.sum()
