"""The grid field's compiled lit pass (``kernels/lit_pass.h``, ``compiled_lit_pass.py``) against
the PyTorch pass it replaces in training with deferred colour: the density grid read with
gradients and its softplus, ``marcher.colour_worthy``, the appearance grid read at the coloured
samples and ``volume_rendering.composite_features_packed``. The same outputs, the same gradient
of every plane and line (dense, and as marked rows for the sparse optimiser), the march's record
the same intervals, points and densities as PyTorch computes, and a training step of each path
from the same state the same loss and the same gradients of every parameter."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from conftest import deferred_grid_model, rays_through_box
from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.field_components.compiled_grid import channel_rows
from nerf_backend.field_components.compiled_lit_pass import lit_pass
from nerf_backend.field_components.grid_encodings import VectorMatrixGrid
from nerf_backend.model_components.compiled_march import compiled_lit_samples
from nerf_backend.model_components.marcher import (TRAIN_COLOURED_WEIGHT, TRAIN_RELATIVE_WEIGHT, colour_worthy,
                                                   lit_intervals)
from nerf_backend.model_components.volume_rendering import composite_features_packed
from nerf_backend.models.registry import build_model
from nerf_backend.training.sparse_adam import RowGradients

COLOURING = (TRAIN_COLOURED_WEIGHT, TRAIN_RELATIVE_WEIGHT)
BOX = SceneBounds((-1.0, -1.2, -0.8), (1.0, 1.2, 0.8))  # not a cube: the axes must not be swapped
SCALE, SHIFT = 3.0, -1.0


def _grids(seed: int) -> tuple[VectorMatrixGrid, VectorMatrixGrid]:
    """A density grid of 8 channels and an appearance grid of 16 on vertices that differ by axis
    (a swapped axis reads other rows), random values."""
    torch.manual_seed(seed)
    density, appearance = VectorMatrixGrid(8, (9, 7, 5)), VectorMatrixGrid(16, (9, 7, 5))
    with torch.no_grad():
        for parameter in [*density.parameters(), *appearance.parameters()]:
            parameter.normal_(0.0, 0.7)
    return density, appearance


def _samples(density: VectorMatrixGrid, rays: int, steps: int, seed: int):
    """Lit samples as the march gives them: sorted flat indices (some rays with none), their
    march weights spread over 1e-8 .. 1 (so each side of colour_worthy's thresholds is met), and
    records whose density pre-activation is the grid's own at the point."""
    generator = torch.Generator().manual_seed(seed)
    keep = torch.rand(rays * steps, generator=generator) < 0.3
    keep[: steps] = False  # ray 0 has no samples
    lit = keep.nonzero().squeeze(1)
    count = lit.numel()
    t_mid = 1.0 + (lit % steps).float() * 0.1
    delta = 0.02 + 0.2 * torch.rand(count, generator=generator)
    points = torch.rand((count, 3), generator=generator) * 2.0 - 1.0
    points[:5] = torch.tensor([-1.0, 1.0, 0.0])  # the grid's very corners
    with torch.no_grad():
        summed = density._forward_rows(points).sum(dim=1)
    record = torch.cat([t_mid[:, None], delta[:, None], summed[:, None], points], dim=1)
    weight = 10.0 ** (-8.0 * torch.rand(count, generator=generator))
    return lit, weight, record


def _reference(density: VectorMatrixGrid, appearance: VectorMatrixGrid, lit, weight, record, rays, steps):
    """The PyTorch pass: each grid read through embedding_bag (``_forward_rows``), the samples to
    colour chosen by ``colour_worthy``, the compositing ``composite_features_packed``."""
    ray = lit // steps
    points = record[:, 3:]
    sigma = SCALE * torch.nn.functional.softplus(density._forward_rows(points).sum(dim=1) + SHIFT)
    coloured = colour_worthy(weight, ray, rays)
    features = appearance._forward_rows(points.index_select(0, coloured))
    return composite_features_packed(sigma, record[:, 1], record[:, 0], ray, coloured, features, rays), coloured


def _loss(outputs, seed: int) -> torch.Tensor:
    """A random linear function of every output, so each one's gradient counts."""
    generator = torch.Generator().manual_seed(seed)
    return sum((torch.randn(o.shape, generator=generator) * o).sum() for o in outputs)


def _gradients(*grids: VectorMatrixGrid) -> list[torch.Tensor]:
    return [p.grad.clone() for grid in grids for p in grid.sparse_row_parameters()]


def test_the_compiled_lit_pass_gives_the_pytorch_pass_outputs_and_gradients():
    rays, steps = 60, 24
    density, appearance = _grids(0)
    lit, weight, record = _samples(density, rays, steps, 1)
    expected, coloured = _reference(density, appearance, lit, weight, record, rays, steps)
    _loss(expected, 2).backward()
    wanted = _gradients(density, appearance)
    for parameter in [*density.parameters(), *appearance.parameters()]:
        parameter.grad = None
    out = lit_pass(density, appearance, SCALE, SHIFT, lit, weight, record, rays, steps, COLOURING)
    if out is None:
        pytest.skip("no C compiler")
    *compiled, coloured_count = out
    assert coloured_count == coloured.numel() and 0 < coloured_count < lit.numel()
    for got, want in zip(compiled, expected):  # opacity, depth, coloured weight, features
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    _loss(compiled, 2).backward()
    for got, want in zip(_gradients(density, appearance), wanted):
        assert want.abs().max() > 1e-3  # every plane and line has gradient to compare
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)


def test_the_lit_pass_adds_into_the_sparse_optimisers_rows_and_marks_exactly_the_rows_read():
    rays, steps = 40, 16
    density, appearance = _grids(3)
    lit, weight, record = _samples(density, rays, steps, 4)
    out = lit_pass(density, appearance, SCALE, SHIFT, lit, weight, record, rays, steps, COLOURING)
    if out is None:
        pytest.skip("no C compiler")
    _loss(out[:4], 5).backward()
    dense = _gradients(density, appearance)
    sinks = []
    for grid in (density, appearance):
        grid.zero_grad(set_to_none=True)
        grid.row_gradients = RowGradients(grid.sparse_row_parameters())
        sinks.append(grid.row_gradients)
    out = lit_pass(density, appearance, SCALE, SHIFT, lit, weight, record, rays, steps, COLOURING)
    _loss(out[:4], 5).backward()
    rows = [rows for sink in sinks for rows in sink.gradients]
    marks = [marks for sink in sinks for marks in sink.marks]
    assert all(p.grad is None for grid in (density, appearance) for p in grid.parameters())
    for want, got, marked in zip(dense, rows, marks):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
        want_rows = channel_rows(want)
        # a row read with a zero hat weight is marked without gradient: marks cover the gradient
        assert bool((marked.bool() | (want_rows.abs().sum(dim=1) == 0)).all())
        assert bool(marked.bool()[want_rows.abs().sum(dim=1) > 0].all())


def _model(seed: int) -> torch.nn.Module:
    return deferred_grid_model(BOX, seed).train()


def test_the_marchs_record_holds_the_intervals_points_and_density_pytorch_computes():
    model = _model(6)
    density = model.field.compiled_density()
    if density is None:
        pytest.skip("no C compiler")
    origins, directions, t_near, t_far = rays_through_box(BOX, 512, seed=6)
    offset = torch.rand((512, 1), generator=torch.Generator().manual_seed(7))
    march = compiled_lit_samples(model.occupancy, model.step, model.samples_per_ray, density, record=True)
    lit, weight, record = march(origins, directions, t_near, t_far, offset)
    plain_lit, plain_weight = compiled_lit_samples(model.occupancy, model.step, model.samples_per_ray,
                                                   density)(origins, directions, t_near, t_far, offset)
    assert torch.equal(lit, plain_lit) and torch.equal(weight, plain_weight) and lit.numel() > 1000
    low, high = lit_intervals(lit, t_near, t_far, model.step, model.samples_per_ray, offset)
    torch.testing.assert_close(record[:, 0], 0.5 * (low + high), rtol=0, atol=2e-6)
    torch.testing.assert_close(record[:, 1], high - low, rtol=0, atol=2e-6)
    ray = lit // model.samples_per_ray
    points = origins.index_select(0, ray) + directions.index_select(0, ray) * record[:, :1]
    torch.testing.assert_close(record[:, 3:], model.field.normalise(points), rtol=0, atol=2e-6)
    with torch.no_grad():
        summed = model.field.density_grid._forward_rows(record[:, 3:]).sum(dim=1)
    torch.testing.assert_close(record[:, 2], summed, rtol=1e-5, atol=1e-5)


def test_a_training_step_through_the_lit_pass_gives_the_pytorch_steps_loss_and_gradients(monkeypatch):
    """The whole training render of a deferred-colour grid model, the compiled lit pass against
    the PyTorch pass it replaces, from the same state and the same rays: the same loss, and the
    same gradient of every parameter (the grids', the colour network's, the appearance basis')."""
    model = _model(8)
    if model.field.compiled_lit_pass() is None:
        pytest.skip("no C compiler")
    origins, directions, t_near, t_far = rays_through_box(BOX, 512, seed=9)
    target = torch.rand((512, 3), generator=torch.Generator().manual_seed(10))

    def step() -> tuple[float, list[torch.Tensor]]:
        model.zero_grad(set_to_none=True)
        out = model(origins, directions, t_near, t_far, background=1.0, generator=torch.Generator().manual_seed(11))
        loss = ((out[0].rgb - target) ** 2).mean()
        loss.backward()
        return float(loss.detach()), [p.grad.clone() for p in model.parameters() if p.grad is not None]

    compiled_loss, compiled = step()
    monkeypatch.setattr(type(model.field), "compiled_lit_pass", lambda self: None)
    reference_loss, reference = step()
    assert len(compiled) == len(reference) == len(list(model.parameters()))
    assert compiled_loss == pytest.approx(reference_loss, rel=1e-5)
    for got, want in zip(compiled, reference):
        torch.testing.assert_close(got, want, rtol=1e-3, atol=1e-6)


def test_the_pytorch_pass_is_what_runs_where_the_lit_pass_does_not_apply():
    """Per-sample colour, region-aware colour and a grid of channels not in blocks of 8 keep the
    PyTorch pass (``compiled_lit_pass`` None), so nothing they need is skipped."""
    auto = PRESETS["auto"]
    for grid in (dataclasses.replace(auto.grid, deferred_colour=False),
                 dataclasses.replace(auto.grid, deferred_colour=True, region_appearance=True, view_dependent=True),
                 dataclasses.replace(auto.grid, deferred_colour=True, density_channels=12)):
        model = build_model(auto.with_settings(grid=grid), BOX)
        assert model.field.compiled_lit_pass() is None, grid
    model = build_model(auto.with_settings(grid=dataclasses.replace(auto.grid, deferred_colour=True)), BOX)
    assert model.field.compiled_lit_pass() is not None
