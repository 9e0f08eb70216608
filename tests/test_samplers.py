"""Stratified and importance sampling."""

import numpy as np
import pytest
import torch

from nerf_backend.model_components.samplers import merge_edges, sample_pdf, stratified_edges


def test_stratified_jitter_keeps_one_sample_per_stratum():
    near, far = torch.full((500,), 2.0), torch.full((500,), 6.0)
    edges = stratified_edges(near, far, 8, jitter=True, generator=torch.Generator().manual_seed(0))
    assert torch.all(edges[:, 0] == 2.0) and torch.all(edges[:, -1] == 6.0)
    assert torch.all(edges[:, 1:] >= edges[:, :-1])
    # Each interior edge stays within half a bin (0.25) of its uniform position.
    uniform = torch.linspace(2.0, 6.0, 9)
    assert (edges - uniform).abs().max() <= 0.25 + 1e-6
    assert (edges[:, 1:-1] - uniform[1:-1]).std() > 0.1  # and really moves


def test_importance_samples_follow_a_piecewise_constant_pdf():
    edges = torch.tensor([[0.0, 1.0, 2.0, 3.0, 5.0]]).repeat(4, 1)
    weights = torch.tensor([[0.1, 0.0, 0.6, 0.3]]).repeat(4, 1)
    samples = sample_pdf(edges, weights, 50_000, deterministic=False,
                         generator=torch.Generator().manual_seed(1)).flatten().numpy()
    counts, _ = np.histogram(samples, bins=[0, 1, 2, 3, 5])
    fractions = counts / samples.size
    # 200k draws: the binomial standard error is ≤ 0.0011, so 0.005 is > 4 sigma.
    assert fractions == pytest.approx([0.1, 0.0, 0.6, 0.3], abs=0.005)
    # Inside a bin the density is uniform: the last bin [3, 5] splits its mass evenly.
    in_last = samples[samples >= 3]
    assert (in_last < 4).mean() == pytest.approx(0.5, abs=0.01)


def test_deterministic_quantiles_are_exact():
    edges = torch.tensor([[0.0, 1.0, 2.0]])
    t = sample_pdf(edges, torch.tensor([[1.0, 3.0]]), 4, deterministic=True)
    # cdf: 0 → 0.25 at t=1 → 1 at t=2; quantiles 0.125, 0.375, 0.625, 0.875.
    assert t.tolist()[0] == pytest.approx([0.5, 1 + 0.125 / 0.75, 1 + 0.375 / 0.75, 1 + 0.625 / 0.75])


def test_all_zero_weights_fall_back_to_uniform():
    edges = torch.linspace(2, 6, 17).expand(3, 17)
    t = sample_pdf(edges, torch.zeros(3, 16), 8, deterministic=True)
    assert torch.isfinite(t).all()
    assert torch.allclose(t[0], 2 + 4 * (torch.arange(8) + 0.5) / 8)


def test_all_weight_in_one_bin_stays_in_that_bin():
    edges = torch.linspace(0, 1, 11).expand(2, 11)
    weights = torch.zeros(2, 10)
    weights[:, 3] = 1.0
    t = sample_pdf(edges, weights, 100, deterministic=False, generator=torch.Generator().manual_seed(2))
    assert (t >= 0.3 - 1e-6).all() and (t <= 0.4 + 1e-6).all()


def test_merged_edges_are_sorted_union():
    edges = torch.tensor([[0.0, 1.0, 2.0]])
    merged = merge_edges(edges, torch.tensor([[1.5, 0.5]]))
    assert merged.tolist() == [[0.0, 0.5, 1.0, 1.5, 2.0]]
