"""Volume rendering against closed forms."""

import math

import pytest
import torch

from nerf_backend.model_components.samplers import interval_midpoints, stratified_edges
from nerf_backend.model_components.volume_rendering import (composite_rgb, expected_depth, render_weights,
                                                            render_weights_packed, sum_per_ray)


def _uniform_ray(near=2.0, far=6.0, samples=256):
    edges = stratified_edges(torch.tensor([near], dtype=torch.float64), torch.tensor([far], dtype=torch.float64),
                             samples, jitter=False)
    return edges, edges[:, 1:] - edges[:, :-1]


@pytest.mark.parametrize("sigma", [0.05, 0.5, 3.0])
def test_constant_density_matches_beer_lambert(sigma):
    edges, deltas = _uniform_ray()
    density = torch.full_like(deltas, sigma)
    weights, transmittance = render_weights(density, deltas)
    # Opacity of a homogeneous slab of length 4: 1 - exp(-4σ), exact for any discretisation.
    assert weights.sum().item() == pytest.approx(1 - math.exp(-4 * sigma), abs=1e-12)
    # Transmittance in front of sample i: exp(-σ (t_i - near)).
    assert torch.allclose(transmittance[0], torch.exp(-sigma * (edges[0, :-1] - 2.0)), atol=1e-12)
    # Expected depth: ∫ t σ e^{-σ(t-n)} dt over [n, f]; the midpoint rule is O(δ²) accurate.
    n, f = 2.0, 6.0
    exact = (n + 1 / sigma) - (f + 1 / sigma) * math.exp(-sigma * (f - n))
    assert expected_depth(weights, interval_midpoints(edges)).item() == pytest.approx(exact, rel=1e-4)
    # A constant colour over a white background blends by the opacity.
    colour = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64).expand(1, deltas.shape[1], 3)
    opacity = 1 - math.exp(-4 * sigma)
    expected = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64) * opacity + (1 - opacity)
    assert torch.allclose(composite_rgb(weights, colour, 1.0)[0], expected, atol=1e-12)


def test_opaque_wall_takes_all_weight_at_its_first_sample():
    edges, deltas = _uniform_ray(samples=100)
    density = torch.zeros_like(deltas)
    density[0, 40:] = 1e6  # a wall starting at sample 40
    weights, _ = render_weights(density, deltas)
    assert weights[0, 40].item() == pytest.approx(1.0, abs=1e-12)
    assert weights[0, :40].abs().max().item() == 0.0
    assert weights[0, 41:].max().item() < 1e-12
    depth = expected_depth(weights, interval_midpoints(edges)).item()
    assert depth == pytest.approx(interval_midpoints(edges)[0, 40].item(), abs=1e-9)


def test_empty_ray_renders_the_background():
    _, deltas = _uniform_ray(samples=64)
    weights, transmittance = render_weights(torch.zeros_like(deltas), deltas)
    assert weights.abs().max().item() == 0.0
    assert torch.all(transmittance == 1.0)
    rgb = composite_rgb(weights, torch.rand(1, 64, 3, dtype=torch.float64), 1.0)
    assert torch.equal(rgb, torch.ones(1, 3, dtype=torch.float64))


def test_weights_sum_to_one_minus_final_transmittance():
    generator = torch.Generator().manual_seed(0)
    density = torch.rand(32, 128, generator=generator, dtype=torch.float64) * 5
    density[:, ::7] = 0.0
    deltas = torch.rand(32, 128, generator=generator, dtype=torch.float64) * 0.05
    weights, transmittance = render_weights(density, deltas)
    final_transmittance = transmittance[:, -1] * torch.exp(-density[:, -1] * deltas[:, -1])
    assert torch.allclose(weights.sum(-1), 1 - final_transmittance, atol=1e-12)
    assert (weights >= 0).all()


@pytest.mark.parametrize("scale", [1.0, 300.0])  # translucent haze; opaque walls in front of more samples
def test_packed_compositing_equals_the_dense_one_and_its_gradients(scale):
    """The same samples composited packed per ray (only those with density) and as ``[R, S]``
    tensors of every step: the colour, depth and opacity, and the gradients of density and
    colour, agree to float32 rounding."""
    generator = torch.Generator().manual_seed(3)
    rays, steps = 64, 48
    holds = torch.rand(rays, steps, generator=generator) < 0.3  # 30 % of the steps hold density
    lit = holds.view(-1).nonzero().squeeze(1)
    ray = lit // steps
    density = (torch.rand(lit.numel(), generator=generator) * scale).requires_grad_()
    colour = torch.rand(lit.numel(), 3, generator=generator).requires_grad_()
    deltas = torch.rand(rays, steps, generator=generator) * 0.02
    t_mid = torch.cumsum(deltas, 1)
    background = torch.rand(rays, 3, generator=generator)
    upstream = [torch.randn(rays, 3, generator=generator), torch.randn(rays, generator=generator),
                torch.randn(rays, generator=generator)]

    def dense():
        weights, _ = render_weights(density.new_zeros(rays * steps).index_put((lit,), density).view(rays, steps), deltas)
        rgb = colour.new_zeros(rays * steps, 3).index_put((lit,), colour).view(rays, steps, 3)
        return composite_rgb(weights, rgb, background), expected_depth(weights, t_mid), weights.sum(-1)

    def packed():
        weights, _ = render_weights_packed(density, deltas.view(-1)[lit], ray)
        opacity = sum_per_ray(weights, ray, rays)
        rgb = sum_per_ray(weights[:, None] * colour, ray, rays) + (1 - opacity)[:, None] * background
        return rgb, sum_per_ray(weights * t_mid.view(-1)[lit], ray, rays), opacity

    results = {}
    for name, render in (("dense", dense), ("packed", packed)):
        outputs = render()
        gradients = torch.autograd.grad(sum((o * u).sum() for o, u in zip(outputs, upstream)), (density, colour))
        results[name] = (*outputs, *gradients)
    assert float(results["dense"][2].detach().max()) > (0.99 if scale > 1 else 0.05)  # opaque rays, or none
    for dense_value, packed_value in zip(results["dense"], results["packed"]):
        assert torch.allclose(packed_value, dense_value, rtol=1e-4, atol=1e-5)
