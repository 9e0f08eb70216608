"""The compiled distance transform (kernels/distance_transform.c) against scipy's, the
reference it replaces, and the fallback to scipy where no kernel is built."""

import numpy as np
import pytest
import torch
from scipy import ndimage

from nerf_backend.field_components import distance_transform
from nerf_backend.field_components.distance_transform import distance_to_unset
from nerf_backend.kernels.build import load_kernel

SHAPES = [(1, 1, 5), (7, 1, 1), (1, 9, 1), (5, 6, 7), (17, 3, 29), (31, 32, 33)]


@pytest.fixture(scope="module", autouse=True)
def kernel():
    library, reason = load_kernel("distance_transform")
    assert library is not None, reason  # the machines that test have a compiler


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("shape", SHAPES)
def test_the_kernel_gives_scipys_distances(shape, threads, monkeypatch):
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    rng = np.random.default_rng(sum(shape))
    for share_set in (0.3, 0.9, 0.99, 0.999):
        mask = rng.random(shape) < share_set
        if mask.all():
            continue
        expected = ndimage.distance_transform_edt(mask)
        got = distance_to_unset(mask)
        assert got.dtype == np.float32 and got.shape == mask.shape
        # Squared distances are exact integers in float: the two differ by sqrt's rounding.
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=0)


def test_one_unset_cell_gives_the_distance_to_it_everywhere():
    mask = np.ones((20, 31, 12), bool)
    mask[3, 17, 9] = False
    cells = np.stack(np.meshgrid(*(np.arange(n) for n in mask.shape), indexing="ij"), axis=-1)
    exact = np.linalg.norm(cells - np.array([3, 17, 9]), axis=-1)
    np.testing.assert_allclose(distance_to_unset(mask), exact, rtol=1e-6)


def test_no_set_cell_is_zero_and_no_unset_cell_is_infinite():
    assert not distance_to_unset(np.zeros((4, 5, 6), bool)).any()
    assert np.isinf(distance_to_unset(np.ones((4, 5, 6), bool))).all()


def test_a_mask_that_is_not_3d_is_refused():
    with pytest.raises(ValueError, match=r"3-D mask, not one of shape \(4, 4\)"):
        distance_to_unset(np.ones((4, 4), bool))


def test_without_the_kernel_scipy_gives_the_same(monkeypatch):
    mask = np.random.default_rng(1).random((9, 10, 11)) < 0.9
    compiled = distance_to_unset(mask)
    monkeypatch.setattr(distance_transform, "kernel_or_note", lambda name, instead: (None, "no C compiler"))
    fallback = distance_to_unset(mask)
    assert fallback.dtype == np.float32
    np.testing.assert_allclose(fallback, compiled, rtol=1e-6)
