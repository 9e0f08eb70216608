"""Volume rendering, sampling and ray bounds at the extremes: what must come out when the
density is 0, tiny, huge or a spike, when intervals vanish or reach far away, when rays
miss, graze or start inside the box, and when importance sampling gets no weight or all
of it in one bin. Every case asserts: finite outputs and gradients, opacity in [0, 1],
weights ≥ 0 summing to at most 1."""

from __future__ import annotations

import math

import pytest
import torch

from nerf_backend.core.cameras import Intrinsics, camera_rays, pixel_centres, ray_box_intersection
from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.fields.mlp_field import FieldConfig, NerfField
from nerf_backend.models.registry import GridModel
from nerf_backend.model_components.samplers import SamplingConfig
from nerf_backend.models.nerf import render_rays
from nerf_backend.model_components.samplers import sample_pdf, stratified_edges
from nerf_backend.model_components.volume_rendering import composite_rgb, expected_depth, render_weights

SAMPLES = 64
# float32 sums of S weights each within an ulp of its value: a sum may exceed 1 by S ulps.
SUM_SLACK = SAMPLES * torch.finfo(torch.float32).eps


def _ray(near: float = 2.0, far: float = 6.0, samples: int = SAMPLES) -> tuple[torch.Tensor, torch.Tensor]:
    edges = stratified_edges(torch.tensor([near]), torch.tensor([far]), samples, jitter=False)
    return edges, edges[:, 1:] - edges[:, :-1]


def _check_rendering(density: torch.Tensor, deltas: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Render, backpropagate a loss through colour and depth, and check the invariants."""
    density = density.clone().requires_grad_(True)
    colour = torch.full((*density.shape, 3), 0.5, requires_grad=True)
    weights, transmittance = render_weights(density, deltas)
    rgb = composite_rgb(weights, colour, 1.0)
    depth = expected_depth(weights, torch.cumsum(deltas, dim=-1))
    (rgb.sum() + depth.sum()).backward()
    for name, value in (("weights", weights), ("transmittance", transmittance), ("rgb", rgb), ("depth", depth),
                        ("density gradient", density.grad), ("colour gradient", colour.grad)):
        assert torch.isfinite(value).all(), f"{name} is not finite"
    assert (weights >= 0).all()
    opacity = weights.sum(dim=-1)
    assert (opacity >= 0).all() and (opacity <= 1 + SUM_SLACK).all()
    assert ((rgb >= 0) & (rgb <= 1 + SUM_SLACK)).all()
    return weights.detach(), transmittance.detach()


def test_zero_density_everywhere_is_the_background():
    _, deltas = _ray()
    weights, transmittance = _check_rendering(torch.zeros_like(deltas), deltas)
    assert weights.abs().max() == 0 and (transmittance == 1).all()


def test_tiny_density_keeps_its_relative_precision():
    """σ = 1e-8 over 4 units: opacity 4e-8, which 1 - exp(-x) computed naively in float32
    would round to 0 (its ulp at 1 is 1.2e-7); expm1 keeps it to float32 relative precision."""
    _, deltas = _ray()
    weights, _ = _check_rendering(torch.full_like(deltas, 1e-8), deltas)
    assert weights.sum().item() == pytest.approx(4e-8, rel=1e-5)


@pytest.mark.parametrize("sigma", [1e4, 1e8, 1e15, 1e20, 1e30])
def test_huge_density_is_opaque_at_the_first_sample(sigma):
    """σ·δ up to 6e28 (and beyond float32's range once accumulated): all weight on the
    first sample, nothing behind it, gradients finite."""
    _, deltas = _ray()
    weights, transmittance = _check_rendering(torch.full_like(deltas, sigma), deltas)
    assert weights[0, 0].item() == pytest.approx(1.0, abs=1e-6)
    assert weights[0, 1:].max().item() <= 1e-6 if sigma == 1e4 else weights[0, 1:].max().item() == 0.0
    assert transmittance[0, 0] == 1.0


def test_a_single_spike_takes_the_weight_where_it_is():
    _, deltas = _ray()
    density = torch.zeros_like(deltas)
    density[0, 37] = 1e30
    weights, _ = _check_rendering(density, deltas)
    assert weights[0, 37].item() == 1.0 and weights.sum().item() == 1.0


def test_huge_density_and_huge_interval_overflow_without_nan():
    """σ·δ = 1e30·1e10 is +inf in float32: alpha 1, transmittance behind 0, never inf − inf."""
    deltas = torch.tensor([[1e10, 1e10, 1e10]])
    weights, transmittance = _check_rendering(torch.full_like(deltas, 1e30), deltas)
    assert weights.tolist() == [[1.0, 0.0, 0.0]] and transmittance.tolist() == [[1.0, 0.0, 0.0]]


@pytest.mark.parametrize("delta", [0.0, 1e-30, 1e-12])
def test_vanishing_intervals_carry_no_weight(delta):
    deltas = torch.full((1, SAMPLES), delta)
    weights, _ = _check_rendering(torch.full_like(deltas, 1e4), deltas)
    assert weights.sum().item() == pytest.approx(-math.expm1(-1e4 * delta * SAMPLES), abs=1e-6)


def test_a_zero_length_ray_renders_the_background():
    """near = far: every interval has length 0, every sample sits at near."""
    edges, deltas = _ray(near=3.0, far=3.0)
    assert (edges == 3.0).all() and (deltas == 0).all()
    weights, _ = _check_rendering(torch.full_like(deltas, 1e30), deltas)
    assert weights.abs().max() == 0
    # Importance sampling on it stays at near as well.
    assert (sample_pdf(edges, weights, 16, deterministic=False) == 3.0).all()


def test_last_interval_reaching_far_away_stays_finite():
    """The paper ends each ray with δ = 1e10; this project ends it at far, but a caller's
    long last interval must still integrate exactly: a thin medium there is opaque."""
    edges, deltas = _ray()
    deltas = deltas.clone()
    deltas[0, -1] = 1e10
    weights, _ = _check_rendering(torch.full_like(deltas, 1e-3), deltas)
    inside = 1e-3 * 4.0 * (SAMPLES - 1) / SAMPLES
    assert weights[0, -1].item() == pytest.approx(math.exp(-inside), rel=1e-5)
    assert weights.sum().item() == pytest.approx(1.0, abs=1e-6)


BOX_MIN, BOX_MAX = torch.tensor([-1.0, -1.0, -1.0]), torch.tensor([1.0, 1.0, 1.0])


def test_rays_that_miss_graze_or_start_inside_the_box():
    origins = torch.tensor([
        [0.0, -5.0, 3.0],   # misses above
        [1.0, -5.0, 0.0],   # in the plane of the +x face: tangent
        [1.0, -5.0, 1.0],   # along the box's edge
        [0.0, 0.0, 0.0],    # inside, at the centre
        [0.9, 0.9, 0.9],    # inside, near a corner
        [0.0, -5.0, 0.0],   # straight through
        [-5.0, -5.0, -5.0],  # through two opposite corners
    ])
    directions = torch.tensor([
        [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0], [1.0, 1.0, 1.0],
    ])
    directions = directions / directions.norm(dim=-1, keepdim=True)
    t_near, t_far, hit = ray_box_intersection(origins, directions, BOX_MIN, BOX_MAX)
    assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all()
    assert (t_near >= 0).all() and (t_far >= t_near).all()
    assert hit.tolist() == [False, False, False, True, True, True, True]
    assert (t_far[~hit] == t_near[~hit]).all()  # no length: renders as background
    assert t_near[3].item() == 0.0 and t_far[3].item() == pytest.approx(1.0)
    assert t_near[4].item() == 0.0 and t_far[4].item() == pytest.approx(0.1, abs=1e-6)
    assert (t_near[5].item(), t_far[5].item()) == pytest.approx((4.0, 6.0))
    assert (t_near[6].item(), t_far[6].item()) == pytest.approx((4 * math.sqrt(3), 6 * math.sqrt(3)), rel=1e-6)
    # Negative zero components and rays exactly along an axis give no NaN either.
    t_near, t_far, _ = ray_box_intersection(torch.tensor([[-0.0, 2.0, -0.0]]), torch.tensor([[-0.0, -1.0, 0.0]]),
                                            BOX_MIN, BOX_MAX)
    assert (t_near.item(), t_far.item()) == (1.0, 3.0)


def test_grid_model_renders_and_trains_rays_that_miss_graze_or_start_inside():
    """Through the fast model, training and inference: finite colour in [0, 1], background
    for rays that miss, finite gradients."""
    torch.manual_seed(0)
    model = GridModel(PRESETS["fast"], SceneBounds((-1.0,) * 3, (1.0,) * 3))
    origins = torch.tensor([[0.0, -5.0, 3.0], [1.0, -5.0, 0.0], [0.0, 0.0, 0.0], [0.0, -5.0, 0.0]])
    directions = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    t_near, t_far, hit = ray_box_intersection(origins, directions, BOX_MIN, BOX_MAX)
    with torch.no_grad():  # a dense medium everywhere: every cell occupied
        for plane in model.field.density_grid.planes:
            plane.fill_(1.0)
        for line in model.field.density_grid.lines:
            line.fill_(1.0)
    model.update_occupancy()
    model.train()
    output = model(origins, directions, t_near, t_far, background=torch.zeros(4, 3))[-1]
    output.rgb.sum().backward()
    assert torch.isfinite(output.rgb).all()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    assert output.opacity[~hit].abs().max() == 0 and output.rgb[~hit].abs().max() == 0
    assert output.opacity[hit].min() > 0.99  # a density of 25·softplus(38) a unit is opaque
    model.eval()
    with torch.no_grad():
        image = model(origins, directions, t_near, t_far, background=1.0)[-1]
    assert torch.isfinite(image.rgb).all() and ((image.rgb >= 0) & (image.rgb <= 1)).all()
    assert torch.allclose(image.rgb[~hit], torch.ones(1, 3)) and image.opacity[hit].min() > 0.99


def test_nerf_field_never_makes_nan_far_from_the_scene():
    """Positions up to 1e6 units: the encoding's sines stay in [-1, 1], density ≥ 0."""
    torch.manual_seed(0)
    field = NerfField(FieldConfig(depth=2, width=32, skips=(), density_activation="softplus"))
    positions = torch.tensor([[0.0, 0.0, 0.0], [1e3, -1e3, 0.5], [1e6, 1e6, -1e6], [-1e6, 3.0, 1e-30]])
    density, rgb = field(positions, torch.nn.functional.normalize(torch.ones(4, 3), dim=-1))
    assert torch.isfinite(density).all() and (density >= 0).all()
    assert torch.isfinite(rgb).all() and ((rgb >= 0) & (rgb <= 1)).all()


def test_importance_sampling_with_no_weight_or_all_of_it_in_one_bin():
    edges = stratified_edges(torch.full((4,), 2.0), torch.full((4,), 6.0), 8, jitter=False)
    weights = torch.zeros(4, 8)
    weights[1, 5] = 1e-45  # the smallest float32 (denormal): still one bin
    weights[2, 0] = 1e30   # huge
    weights[3, 7] = 1.0    # the last bin, whose upper cdf edge is exactly 1
    samples = sample_pdf(edges, weights, 128, deterministic=False, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(samples).all()
    assert (samples[:, 1:] >= samples[:, :-1]).all()
    assert samples[0].min() >= 2.0 and samples[0].max() <= 6.0  # uniform over the ray
    for row, bin_index in ((1, 5), (2, 0), (3, 7)):
        lo, hi = edges[row, bin_index].item(), edges[row, bin_index + 1].item()
        assert samples[row].min() >= lo and samples[row].max() <= hi


def test_hierarchical_rendering_of_an_empty_and_an_opaque_field():
    """The paper's coarse-to-fine path with a field that is empty everywhere and one that is
    opaque everywhere: finite, fine samples inside [near, far], gradients finite."""

    class ConstantField(torch.nn.Module):
        def __init__(self, sigma: float) -> None:
            super().__init__()
            self.scale = torch.nn.Parameter(torch.tensor(1.0))
            self.sigma = sigma

        def forward(self, positions, directions):
            density = self.scale * torch.full(positions.shape[:-1], self.sigma)
            return density, torch.sigmoid(self.scale * positions)

    origins = torch.tensor([[0.0, -4.0, 0.0], [0.0, -4.0, 0.0]])
    directions = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    t_near, t_far = torch.tensor([2.0, 3.0]), torch.tensor([6.0, 3.0])  # the second ray has no length
    for sigma in (0.0, 1e30):
        coarse, fine = ConstantField(sigma), ConstantField(sigma)
        outputs = render_rays(coarse, fine, origins, directions, t_near, t_far, SamplingConfig(16, 16), 1.0,
                              training=True, generator=torch.Generator().manual_seed(0))
        (outputs[0].rgb.sum() + outputs[1].rgb.sum()).backward()
        for output in outputs:
            assert torch.isfinite(output.rgb).all() and torch.isfinite(output.depth).all()
            assert ((output.opacity >= 0) & (output.opacity <= 1 + SUM_SLACK)).all()
            assert output.opacity[1] == 0  # the zero-length ray is background
        assert output.t_edges[0].min() >= 2.0 and output.t_edges[0].max() <= 6.0
        assert torch.isfinite(coarse.scale.grad) and torch.isfinite(fine.scale.grad)
        assert outputs[1].opacity[0].item() == pytest.approx(0.0 if sigma == 0 else 1.0, abs=1e-6)


@pytest.mark.parametrize("camera_angle_x", [1e-4, 0.6911112070083618, 2.0, math.pi - 1e-3])
@pytest.mark.parametrize("size", [1, 2, 801])
def test_camera_rays_from_very_narrow_to_very_wide_lenses(camera_angle_x, size):
    """Unit, finite directions at 1e-4 rad (a 1e6 mm lens on a 36 mm sensor) up to 179.9°,
    at 1×1 pixels as well; the edge pixel's ray makes the expected angle with the axis."""
    intrinsics = Intrinsics.from_camera_angle_x(size, size, camera_angle_x)
    index = torch.arange(size * size)
    origins, directions = camera_rays(intrinsics, torch.eye(4), pixel_centres(size, index))
    assert torch.isfinite(directions).all()
    assert torch.allclose(directions.norm(dim=-1), torch.ones(size * size), atol=1e-6)
    left_edge = camera_rays(intrinsics, torch.eye(4), torch.tensor([[0.0, size / 2]]))[1][0]
    # atan2, not acos: cos(5e-5) rounds to 1 in float32, the sine keeps its precision.
    angle = math.atan2(left_edge[:2].norm().item(), -left_edge[2].item())
    assert angle == pytest.approx(camera_angle_x / 2, rel=1e-5)
