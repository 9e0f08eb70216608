"""The occupancy grid's cells from the grid field's dense sums in one compiled pass
(``occupancy.cells_over``, ``kernels/occupied_cells.c``) against PyTorch's cell maxima, and
the grid field's ``occupied_cells`` against the rule it shortcuts (``MarchableField``'s)."""

from __future__ import annotations

import pytest
import torch

from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.fields.base import MarchableField, cell_corner_max
from nerf_backend.kernels.build import load_kernel
from nerf_backend.model_components.occupancy import cells_exceeding, cells_over
from nerf_backend.models.registry import GridModel

pytestmark = pytest.mark.skipif(load_kernel("occupied_cells")[0] is None, reason="no C compiler")

BOX = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _reference(sums: torch.Tensor, above: float, shift: float, allowed: torch.Tensor | None):
    cell_max = cell_corner_max(sums.double()).permute(2, 1, 0)  # [Gx, Gy, Gz]

    def excess(values: torch.Tensor) -> float:
        return float((values + shift).clamp_min(0).nan_to_num(0.0).sum())

    return cells_exceeding(cell_max, above, allowed), excess(sums.double()), excess(cell_max)


# Sizes around the kernel's blocks: 8-byte transposes, tiles of 64 cells along z, and a
# thread's share of y; 2 vertices an axis is the smallest grid.
@pytest.mark.parametrize("shape", [(2, 2, 2), (9, 3, 17), (66, 5, 10), (130, 12, 33), (65, 9, 8)])
@pytest.mark.parametrize("threads", [1, 3])
def test_the_cells_and_the_bounds_equal_pytorchs(shape, threads):
    torch.manual_seed(sum(shape) + threads)
    sums = torch.randn(shape) * 4.0
    sums[torch.rand(shape) < 0.01] = float("nan")  # a NaN corner leaves its cell unmarked
    allowed = torch.rand(shape[2] - 1, shape[1] - 1, shape[0] - 1) < 0.7
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for may in (None, allowed):
            for above in (-float("inf"), 0.5, 3.0):
                occupied, vertex_excess, cell_excess = cells_over(sums, above, -1.0, may)
                expected, expected_vertex, expected_cell = _reference(sums, above, -1.0, may)
                assert occupied.dtype == torch.bool and occupied.shape == expected.shape
                assert torch.equal(occupied, expected)
                # float lanes, then double: within 1e-5 of the double reference's sums
                assert vertex_excess == pytest.approx(expected_vertex, rel=1e-5, abs=1e-6)
                assert cell_excess == pytest.approx(expected_cell, rel=1e-5, abs=1e-6)
    finally:
        torch.set_num_threads(before)


def test_a_threshold_between_two_floats_is_compared_as_the_double_it_is():
    """``above`` need not be a float: a sum exactly at the float below it is not above it,
    the float after that is."""
    sums = torch.zeros(2, 2, 3)
    sums[0, 0, 0] = 1.0
    sums[0, 0, 2] = float(torch.nextafter(torch.tensor(1.0), torch.tensor(2.0)))
    occupied, _, _ = cells_over(sums, 1.0 + 1e-9, 0.0)
    assert occupied.flatten().tolist() == [False, True]


def test_cells_over_says_where_it_does_not_apply():
    assert cells_over(torch.zeros(2, 2, 2, dtype=torch.float64), 0.0, 0.0) is None
    assert cells_over(torch.zeros(1, 4, 4), 0.0, 0.0) is None
    with pytest.raises(ValueError, match="allowed cells"):
        cells_over(torch.zeros(3, 3, 3), 0.0, 0.0, torch.ones(3, 3, 3, dtype=torch.bool))


def _structured_model(seed: int, spread: float) -> GridModel:
    torch.manual_seed(seed)
    model = GridModel(PRESETS["fast"], BOX)
    with torch.no_grad():  # dense blobs over empty space; a small spread: a faint, young field
        for plane in model.field.density_grid.planes:
            plane.normal_(0.0, spread)
    return model


@pytest.mark.parametrize("spread", [6.0, 0.01], ids=["trained", "faint"])
@pytest.mark.parametrize("rendering", [False, True], ids=["training", "rendering"])
def test_the_grid_field_marks_the_cells_the_rule_marks(spread, rendering):
    """The compiled shortcut (compare sums, not densities; the mean only where its bound does
    not settle the threshold) against ``MarchableField.occupied_cells`` through PyTorch: the
    same cells, but for any whose largest density lies within float rounding of the
    threshold (none in these fields)."""
    model = _structured_model(3, spread)
    field = model.field
    field.train(not rendering)
    threshold = model.render_density_threshold if rendering else model.density_threshold
    allowed = torch.rand(field.occupancy_cells()) < 0.8
    expected = MarchableField.occupied_cells(field, threshold, allowed, rendering)
    got = field.occupied_cells(threshold, allowed, rendering)
    with torch.no_grad():
        cell_max = field.cell_max_density()
        mean = float(cell_max.mean()) if rendering else float(field.vertex_density().mean())
    assert (mean < threshold) == (spread < 1.0)  # the faint field's mean decides, the other's does not
    assert 0 < int(expected.sum()) < expected.numel()
    assert torch.equal(got, expected)
