"""Deferred colour (``grid.deferred_colour``, SNeRG's deferred shading): the grid field's samples
carry their appearance grid's features, the march composites them along each ray, and the
colour network runs once a ray on their weighted mean (``volume_rendering.shade_rays``).

Checked against hand-written references: an opaque surface gets exactly the colour its own
sample gives without deferral; the training march's image is the definition composited by hand;
the packed training march, both inference marches and the compiled one agree with it to the
bounds of their shortcuts; a faint ray's gradients stay finite; the preset trains end to end."""

from __future__ import annotations

import copy
import ctypes
import json

import numpy as np
import pytest
import torch

from conftest import X86_LEVELS, cpu_runs_x86_level, deferred_grid_model, rays_through_box, run_python
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.data.dataset import load_split
from nerf_backend.field_components.compiled_colour import CompiledRayFeatures
from nerf_backend.field_components.compiled_grid import channel_rows
from nerf_backend.fields import grid_field as grid_field_module
from nerf_backend.fields.grid_field import GridField, GridFieldConfig
from nerf_backend.kernels.build import load_kernel
from nerf_backend.metrics.image_metrics import psnr
from nerf_backend.model_components import marcher
from nerf_backend.model_components.compiled_composite import compiled_composite_features
from nerf_backend.model_components.compiled_march import compiled_lit_samples, compiled_march_library
from nerf_backend.model_components.marcher import OPAQUE_TRANSMITTANCE, SKIPPED_WEIGHT, render_marched_stopping_early
from nerf_backend.model_components.occupancy import OccupancyGrid
from nerf_backend.model_components.volume_rendering import (MIN_SHADED_WEIGHT, composite_features_packed,
                                                             shade_rays)

BOX = SceneBounds((-1.0, -1.2, -0.8), (1.0, 1.2, 0.8))  # not a cube: the axes must not be swapped


def _field(deferred: bool, wall: bool, seed: int = 0) -> GridField:
    """A grid field with random appearance and, with ``wall``, density a function of y alone (a
    faint haze, alpha ~1e-5 a step, for y < 0, then an opaque wall); else smooth random blobs
    of density (random values on a coarse grid, interpolated up), translucent and opaque."""
    torch.manual_seed(seed)
    field = GridField(GridFieldConfig(resolution=40, initial_resolution=40, density_shift=0.0,
                                      density_scale=300.0 if wall else 4.0, deferred_colour=deferred),
                      SceneBounds((-1.0, -1.0, -0.5), (1.0, 1.0, 0.5)))
    vertices = field.vertices
    with torch.no_grad():
        for parameter in field.appearance_grid.parameters():
            parameter.normal_(0.0, 0.5)
        density = field.density_grid
        if wall:
            for parameter in (density.planes[0], density.planes[2], density.lines[0], density.lines[2]):
                parameter.zero_()
            density.planes[1].fill_(1.0)
            y = torch.linspace(-1, 1, density.lines[1].shape[2])
            summed = torch.where(y < 0, -14.0, 3.0) / density.channels
            density.lines[1].copy_(summed.view(1, 1, -1, 1).expand_as(density.lines[1]))
        else:
            density.resize((5, 5, 4))
            for parameter in density.parameters():
                parameter.normal_(0.0, 0.6)
            density.resize(vertices)
    return field


def _rays(count: int = 500, seed: int = 1):
    generator = torch.Generator().manual_seed(seed)
    origins = torch.randn(count, 3, generator=generator) * 0.3 + torch.tensor([0.0, -3.0, 0.0])
    directions = torch.nn.functional.normalize(
        torch.randn(count, 3, generator=generator) * 0.2 + torch.tensor([0.0, 1.0, 0.0]), dim=-1)
    return origins, directions, torch.full((count,), 1.5), torch.full((count,), 4.5), torch.rand(count, 1,
                                                                                                 generator=generator)


def _training_march(field: GridField, rays, packed: bool):
    grid = OccupancyGrid(field.box_min, field.box_max, field.occupancy_cells())
    step, steps = 0.025, 120
    common = dict(density_fn=lambda x, d: field.density(x), occupancy=grid, step=step, steps=steps, background=1.0,
                  offset=rays[4], shade_fn=field.shade_fn())
    if packed:
        lit_fn = compiled_lit_samples(grid, step, steps, field.compiled_density())
        return marcher.render_marched(*rays[:4], field_fn=field, lit_fn=lit_fn, **common)
    return marcher.render_marched(*rays[:4], field_fn=lambda x, d, c=None: GridField.forward(field, x, d), **common)


def test_where_a_rays_samples_share_their_features_its_colour_is_theirs():
    """Deferred colour shades the weighted mean of a ray's features; where every sample has the
    same features (a uniform appearance grid), that mean is those features, and the image
    equals per-sample colour's with the same parameters, translucent rays and opaque ones."""
    fields = [_field(deferred=deferred, wall=False, seed=2) for deferred in (False, True)]
    for field in fields:
        with torch.no_grad():
            for parameter in field.appearance_grid.parameters():
                parameter.copy_(torch.linspace(-0.5, 0.5, parameter.shape[1]).view(1, -1, 1, 1).expand_as(parameter))
    rays = _rays(seed=3)
    per_sample, deferred = (_training_march(field, rays, packed=False) for field in fields)
    opacity = per_sample.opacity.detach()
    assert float(((opacity > 0.05) & (opacity < 0.95)).float().mean()) > 0.1  # translucent rays
    assert float((opacity > 0.99).float().mean()) > 0.1  # nearly opaque ones
    assert torch.allclose(deferred.rgb.detach(), per_sample.rgb.detach(), atol=1e-5)


def test_the_training_march_is_the_shaded_mean_of_the_features_composited_by_hand():
    """``render_marched`` (every lit sample) against the definition written out: the weights of
    the march, each sample's appearance features, their weighted mean per ray, the network on
    it, times the opacity, over the background. Then the packed march (the compiled one, which
    leaves the faintest samples out of the mean) within the weight it leaves out, and every
    part of the field gets finite gradients."""
    field = _field(deferred=True, wall=False, seed=2)
    rays = _rays(seed=3)
    dense = _training_march(field, rays, packed=False)
    origins, directions, near, far, offset = rays
    edges = marcher.march_edges(near, far, 0.025, offset, 0, 120)
    positions = origins[:, None] + directions[:, None] * marcher.interval_midpoints(edges)[..., None]
    with torch.no_grad():
        features = field.appearance_grid(field.normalise(positions.view(-1, 3))).view(500, 120, -1)
        weights = dense.weights.detach()
        opacity = weights.sum(dim=1)
        mean = (weights[..., None] * features).sum(dim=1) / opacity.clamp_min(1e-30)[:, None]
        shaded = field.colour_from_grid(mean, field.direction_inputs(directions))
        expected = opacity[:, None] * shaded + (1 - opacity)[:, None]
    assert 0.05 < float(opacity.mean()) < 0.95  # translucent rays and opaque ones
    assert torch.allclose(dense.rgb.detach(), expected, atol=1e-5)
    packed = _training_march(field, rays, packed=True)
    assert torch.allclose(packed.opacity, dense.opacity, atol=1e-5)
    difference = (packed.rgb - dense.rgb).detach().abs()
    assert float(difference.max()) < 1e-2 and float(difference.mean()) < 1e-4
    packed.rgb.sum().backward()
    for name, parameter in field.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name
        assert float(parameter.grad.abs().max()) > 0, name


@pytest.mark.parametrize("deferred", [False, True])
def test_read_by_pytorch_the_field_gives_what_its_compiled_read_gives(deferred, monkeypatch):
    """On CUDA, MPS or without a C compiler PyTorch reads the grids (``read_grids`` None): the
    field's samples still carry its appearance features with deferred colour (a colour there
    failed lego's first training step on an H200: 3 values where the shading takes 72), and
    the training march's image is the compiled read's."""
    field = _field(deferred=deferred, wall=False, seed=2)
    generator = torch.Generator().manual_seed(4)
    x = torch.rand(400, 3, generator=generator) * 2 - 1
    directions = torch.nn.functional.normalize(torch.randn(400, 3, generator=generator), dim=-1)
    rays = _rays(seed=3)
    with torch.no_grad():
        compiled, compiled_march = field(x, directions), _training_march(field, rays, packed=False)
        monkeypatch.setattr(grid_field_module, "read_grids", lambda grids, points: None)
        plain, plain_march = field(x, directions), _training_march(field, rays, packed=False)
    width = field.appearance_grid.out_dims if deferred else 3
    assert plain[1].shape == compiled[1].shape == (400, width)
    for a, b in zip(plain, compiled):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-5)
    assert torch.allclose(plain_march.rgb, compiled_march.rgb, atol=1e-5)


def test_a_faint_ray_is_shaded_black_and_every_gradient_is_finite():
    """A ray whose coloured weight is under ``MIN_SHADED_WEIGHT`` is black (the network never
    sees it, and it would add about that much to its pixel), down to float32's smallest
    subnormal; the others are their features' colour to float32 rounding."""
    features = torch.randn(4, 6, requires_grad=True)
    coloured = torch.tensor([1e-45, 1e-13, 1e-9, 0.5], requires_grad=True)
    weighted = features * coloured[:, None]  # Σ w·f of one sample each
    network = torch.nn.Linear(6, 3)

    def shade(mean, directions):
        return torch.sigmoid(network(mean))

    rgb = shade_rays(weighted, coloured, coloured, torch.zeros(4, 3), shade)
    rgb.sum().backward()
    assert torch.equal(rgb[:2].detach(), torch.zeros(2, 3))  # under MIN_SHADED_WEIGHT (1e-12)
    expected = coloured[2:, None].detach() * torch.sigmoid(network(features[2:].detach()))
    assert torch.allclose(rgb[2:].detach(), expected, rtol=1e-5, atol=1e-12)
    assert torch.isfinite(features.grad).all() and torch.isfinite(coloured.grad).all()


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("scale", [0.5, 40.0, 1e9], ids=["translucent", "dense", "opaque"])
def test_the_compiled_compositing_equals_pytorchs_and_its_gradients(scale, threads, monkeypatch):
    """``compiled_composite_features`` (kernels/packed_composite.c) against
    ``composite_features_packed``: the four outputs and the gradients of density and features
    for random upstream gradients, to float32 rounding (1e-4 relative to the largest), with rays
    of no samples, rays of one, and rays whose first sample is opaque."""
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    generator = torch.Generator().manual_seed(5)
    rays, channels = 300, 72
    counts = torch.randint(0, 40, (rays,), generator=generator)
    counts[:10] = 0
    counts[10:20] = 1
    ray = torch.repeat_interleave(torch.arange(rays), counts)
    samples = ray.numel()
    density = (torch.rand(samples, generator=generator) * scale).requires_grad_()
    deltas = torch.rand(samples, generator=generator) * 0.05
    t_mid = torch.rand(samples, generator=generator) * 4
    coloured = (torch.rand(samples, generator=generator) < 0.4).nonzero().squeeze(1)
    features = torch.randn(coloured.numel(), channels, generator=generator).requires_grad_()
    upstream = [torch.randn(rays, generator=generator), torch.randn(rays, generator=generator),
                torch.randn(rays, generator=generator), torch.randn(rays, channels, generator=generator)]
    results = []
    for composite in (compiled_composite_features, composite_features_packed):
        outputs = composite(density, deltas, t_mid, ray, coloured, features, rays)
        assert outputs is not None  # the compiled pass applies here (CPU, float32, gcc)
        gradients = torch.autograd.grad(sum((o * u).sum() for o, u in zip(outputs, upstream)), (density, features))
        results.append([t.detach() for t in (*outputs, *gradients)])
    for compiled, reference in zip(*results):
        assert torch.isfinite(compiled).all()
        assert float((compiled - reference).abs().max()) <= 1e-4 * max(1.0, float(reference.abs().max()))


@pytest.mark.parametrize("level", [None, *sorted(X86_LEVELS)])
def test_the_compiled_inference_compositing_adds_each_samples_weighted_features(level):
    """``CompiledRayFeatures.composite`` against the sum written with PyTorch's reads: this
    CPU's build, and each vector width's it runs (conftest's X86_LEVELS)."""
    field = _field(deferred=True, wall=False, seed=6)
    features_fn = field.ray_features(torch.zeros(1, 3))
    assert hasattr(features_fn, "composite")  # the compiled pass applies here
    if level is not None:
        if not cpu_runs_x86_level(level):
            pytest.skip(f"this CPU cannot run code for {level}")
        library, why_not = load_kernel("vm_grid", level)
        assert library is not None, why_not
        library.composite_samples.restype = ctypes.c_int
        features_fn = CompiledRayFeatures(field, library)
    x, ray, weight = _packed_samples()
    out = torch.zeros(50, field.appearance_grid.out_dims)
    features_fn.composite(x, ray, weight, out)
    expected = _composited_through_pytorch(field, x, ray, weight, rays=50)
    if features_fn._halves is None:  # float32 tables: PyTorch's sums to rounding
        assert float((out - expected).abs().max()) <= 1e-5 * float(expected.abs().max())
        return
    # Half-precision tables (x86-64-v3 and up): the sums of the grid rounded to half, to float32
    # rounding; and within the half's rounding (2^-11 of each row value, twice: plane and line)
    # of the float32 grid's.
    expected_rounded = _composited_through_pytorch(_as_read(field, features_fn), x, ray, weight, rays=50)
    assert float((out - expected_rounded).abs().max()) <= 1e-5 * float(expected_rounded.abs().max())
    bound = 2.0 ** -10 * _composited_through_pytorch(field, x, ray, weight, rays=50, magnitudes=True)
    assert bool(((out - expected).abs() <= bound + 1e-6).all())
    assert float((out - expected).abs().max()) > 0  # the half tables were read


def test_the_half_tables_follow_the_grid_and_step_aside_for_values_a_half_cannot_hold():
    """The feature pass's half-precision copy of the appearance grid is made again when the grid
    changes, and not at all where a value is past the half's range (the float32 tables are read,
    to PyTorch's sums)."""
    field = _field(deferred=True, wall=False, seed=6)
    first = field.ray_features(torch.zeros(1, 3))
    if first._halves is None:
        pytest.skip("this build reads float32 tables (no F16C)")
    again = field.ray_features(torch.zeros(1, 3))
    assert again._halves is first._halves  # kept between a view's chunks
    x, ray, weight = _packed_samples()
    with torch.no_grad():
        field.appearance_grid.planes[0].mul_(2.0)
    doubled = field.ray_features(torch.zeros(1, 3))
    assert doubled._halves is not first._halves
    assert torch.equal(doubled._halves[0], channel_rows(field.appearance_grid.planes[0].detach()).half())
    with torch.no_grad():
        field.appearance_grid.lines[2][0, 0, 3, 0] = 1e5  # past 65504
    wide = field.ray_features(torch.zeros(1, 3))
    assert wide._halves is None
    out = torch.zeros(50, field.appearance_grid.out_dims)
    wide.composite(x, ray, weight, out)
    expected = _composited_through_pytorch(field, x, ray, weight, rays=50)
    assert float((out - expected).abs().max()) <= 1e-5 * float(expected.abs().max())


def _packed_samples() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """4 000 packed samples of 50 rays (ascending) in the field's box, and their weights."""
    generator = torch.Generator().manual_seed(7)
    ray = torch.sort(torch.randint(0, 50, (4000,), generator=generator)).values
    x = (torch.rand(4000, 3, generator=generator) * 2 - 1) * torch.tensor([1.0, 1.0, 0.5])
    return x, ray, torch.rand(4000, generator=generator)


def _as_read(field, features_fn):
    """``field`` as the compiled pass ``features_fn`` reads it: its appearance grid rounded to
    half precision where the pass reads half tables."""
    if features_fn._halves is None:
        return field
    rounded = copy.deepcopy(field)
    with torch.no_grad():
        for parameter in rounded.appearance_grid.parameters():
            parameter.copy_(parameter.half().float())
    return rounded


def _composited_through_pytorch(field, x, ray, weight, rays: int, magnitudes: bool = False):
    """Each ray's row: the sum of its samples' weighted appearance features, read by PyTorch;
    with ``magnitudes``, of the grid's absolute values (what bounds a rounding of the rows)."""
    with torch.no_grad():
        grid = field.appearance_grid
        if magnitudes:
            grid = copy.deepcopy(grid)
            for parameter in grid.parameters():
                parameter.abs_()
        features = grid._forward_rows(field.normalise(x))
        return torch.zeros(rays, features.shape[1]).index_add_(0, ray, weight[:, None] * features)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_compiled_compositing_on_threads_keeps_each_rays_sum_whole(threads, monkeypatch):
    """Each thread takes a run of whole rays (its share's end moved on to a ray's start): with
    rays of 1 to 3 000 samples, some longer than a thread's share, every ray's row is its
    samples' sum, the same bits whatever the threads."""
    field = _field(deferred=True, wall=False, seed=8)
    features_fn = field.ray_features(torch.zeros(1, 3))
    generator = torch.Generator().manual_seed(9)
    lengths = torch.cat([torch.tensor([1023, 1, 3000, 1024, 2049]), torch.randint(1, 40, (300,), generator=generator)])
    ray = torch.repeat_interleave(torch.arange(lengths.numel()), lengths)
    points = ray.numel()
    x = (torch.rand(points, 3, generator=generator) * 2 - 1) * torch.tensor([1.0, 1.0, 0.5])
    weight = torch.rand(points, generator=generator)
    rows = {}
    for count in sorted({1, threads}):
        monkeypatch.setattr(torch, "get_num_threads", lambda count=count: count)
        rows[count] = torch.zeros(lengths.numel(), field.appearance_grid.out_dims)
        features_fn.composite(x, ray, weight, rows[count])
    expected = _composited_through_pytorch(_as_read(field, features_fn), x, ray, weight, rays=lengths.numel())
    # colour_network.h's composite_samples gives a thread at least 4 096 samples: enough here for 3.
    assert points > 3 * 4096
    assert torch.equal(rows[threads], rows[1])
    assert float((rows[threads] - expected).abs().max()) <= 1e-5 * float(expected.abs().max())


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_fresh_rows_are_set_to_their_rays_sums_and_the_rows_no_sample_reaches_are_left(threads, monkeypatch):
    """``composite(..., fresh=True)`` (the render march's: each ray's samples in one call) into
    rows holding NaN: each reached row is, bit for bit, the sum the call adds to a zeroed row,
    over two calls split at a ray's end and on 1-3 threads; the rows of rays with no samples
    (every third ray) are not written."""
    field = _field(deferred=True, wall=False, seed=8)
    features_fn = field.ray_features(torch.zeros(1, 3))
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    generator = torch.Generator().manual_seed(10)
    lengths = torch.randint(1, 80, (400,), generator=generator)
    lengths[::3] = 0
    ray = torch.repeat_interleave(torch.arange(lengths.numel()), lengths)
    points = ray.numel()
    x = (torch.rand(points, 3, generator=generator) * 2 - 1) * torch.tensor([1.0, 1.0, 0.5])
    weight = torch.rand(points, generator=generator)
    added = torch.zeros(lengths.numel(), field.appearance_grid.out_dims)
    features_fn.composite(x, ray, weight, added)
    fresh = torch.full_like(added, float("nan"))
    split = int((ray < 200).sum())  # ray 199's last sample ends the first call
    assert 0 < split < points and int(ray[split - 1]) != int(ray[split])
    for part in (slice(0, split), slice(split, points)):
        features_fn.composite(x[part], ray[part], weight[part], fresh, fresh=True)
    reached = lengths > 0
    assert torch.equal(fresh[reached], added[reached])
    assert bool(fresh[~reached].isnan().all()) and bool((added[reached] != 0).any())


def _model(seed: int = 3):
    return deferred_grid_model(BOX, seed)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_inference_renders_the_training_marchs_image_in_both_marches(threads, monkeypatch):
    """The model's inference (the compiled march on the CPU) and PyTorch's early-stopping march
    against the training march with gradients (every lit sample in the mean): the same image
    to the bounds of the early stop and of the faint weight left out of the mean."""
    library, reason = compiled_march_library()
    assert library is not None, reason
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    model = _model()
    rays = rays_through_box(BOX, 3000, seed=4)
    with torch.no_grad():
        compiled = model(*rays)[0]
        march = dict(occupancy=model.render_occupancy(), step=model.step, steps=model.samples_per_ray, background=1.0,
                     stop=model.ray_stop)
        early = render_marched_stopping_early(*rays, density_fn=model._frozen_density,
                                              ray_colour=model.field.ray_features(rays[1]),
                                              shade_fn=model.field.shade_fn(), **march)
    with torch.enable_grad():
        full = model(*rays)[0]
    assert full.weights is not None and early.weights is None  # the paths really differ
    opaque = full.opacity > 1 - OPAQUE_TRANSMITTANCE
    assert 0 < opaque.sum() < len(opaque)
    for out in (compiled, early):
        assert (out.opacity - full.opacity).abs().max() < 2 * OPAQUE_TRANSMITTANCE + 1e-5
        # Up to SKIPPED_WEIGHT of a ray's weight is left out of its mean features, which moves the
        # shaded colour of the whole ray a little, not only that weight's share (measured: at
        # most 5.1e-3, 1.8e-4 on average; per-sample colour's average is under 1e-4).
        assert (out.rgb - full.rgb.detach()).abs().max() < 2 * OPAQUE_TRANSMITTANCE + 2 * SKIPPED_WEIGHT
        assert (out.rgb - full.rgb.detach()).abs().mean() < 5e-4
    assert (compiled.rgb - early.rgb).abs().max() < 2 * OPAQUE_TRANSMITTANCE + 2 * SKIPPED_WEIGHT


# The auto preset with deferred colour on the tiny demo, 150 steps of 512 rays: 28.27 dB on the
# AVX-512 Xeon (per-sample colour 28.10; the blank white image 15.43); with its learning rates
# 0, 15.43 dB.
DEFERRED_PSNR_FLOOR_DB = 21.0


def test_the_auto_preset_trains_and_renders_with_deferred_colour(tiny_demo_dataset, tmp_path):
    run = tmp_path / "deferred"
    run_python("-m", "nerf_backend", "train", str(tiny_demo_dataset), "--out", str(run), "--iters", "150",
               "--set", "rays_per_batch=512", "--set", "grid.deferred_colour=true", "--no-progress")
    run_python("-m", "nerf_backend", "eval", str(run), "--no-progress")
    metrics = json.loads((run / "metrics.json").read_text())
    test_split = load_split(tiny_demo_dataset, "test")
    blank = np.mean([psnr(np.ones_like(gt), gt) for gt in test_split.rgb_on_white().numpy()])
    print(f"auto with deferred colour, 150 steps: {metrics['psnr']:.2f} dB (blank {blank:.2f} dB)")
    assert metrics["psnr"] >= DEFERRED_PSNR_FLOOR_DB
    assert json.loads((run / "config.json").read_text())["config"]["grid"]["deferred_colour"] is True
