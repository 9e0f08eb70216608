"""The fast preset's components: factorised grids, the occupancy grid, grid marching."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.field_components.grid_encodings import VectorMatrixGrid
from nerf_backend.models.registry import GridModel
from nerf_backend.models.nerf import NerfModel
from nerf_backend.model_components.marcher import SKIPPED_WEIGHT
from nerf_backend.model_components.occupancy import OccupancyGrid

BOX = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _reference_bilinear(image: torch.Tensor, u: float, v: float) -> torch.Tensor:
    """Bilinear interpolation of ``image [C, H, W]`` at normalised (u → W, v → H) in [-1, 1],
    vertices at the ends (align_corners): written out by hand."""
    _, height, width = image.shape
    x, y = (u + 1) / 2 * (width - 1), (v + 1) / 2 * (height - 1)
    x0, y0 = min(int(math.floor(x)), width - 2), min(int(math.floor(y)), height - 2)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * image[:, y0, x0] + fx * (1 - fy) * image[:, y0, x0 + 1]
            + (1 - fx) * fy * image[:, y0 + 1, x0] + fx * fy * image[:, y0 + 1, x0 + 1])


def test_vector_matrix_interpolation_matches_a_hand_written_reference():
    torch.manual_seed(0)
    grid = VectorMatrixGrid(channels=3, vertices=(9, 7, 5)).double()  # one count per axis
    points = torch.rand(20, 3, dtype=torch.float64) * 2 - 1
    features = grid(points)
    for p, got in zip(points, features):
        expected = []
        for (a, b), line_axis, plane, line in zip(((0, 1), (0, 2), (1, 2)), (2, 1, 0), grid.planes, grid.lines):
            plane_value = _reference_bilinear(plane[0], p[b].item(), p[a].item())  # plane[h=a, w=b]
            line_value = _reference_bilinear(line[0], 0.0, p[line_axis].item())
            expected.append(plane_value * line_value)
        assert torch.allclose(got, torch.cat(expected), atol=1e-12)


def test_the_cpu_row_kernel_reads_the_grid_as_grid_sample_does():
    """The CPU kernel (channel rows through embedding_bag) against grid_sample, features and
    every parameter's gradient, for points inside, on the faces of and outside the grid
    (zero padding: a cell beyond a face fades to 0)."""
    torch.manual_seed(3)
    grid = VectorMatrixGrid(channels=5, vertices=(9, 7, 6)).double()
    points = torch.rand(400, 3, dtype=torch.float64) * 2.6 - 1.3
    points[:6] = torch.tensor([[-1.0, -1, -1], [1, 1, 1], [1, -1, 0.3], [-1.1, 0, 0], [1.6, -1.6, 1.6], [0, 0, 1.05]])
    upstream = torch.randn(400, 15, dtype=torch.float64)
    gradients = []
    for kernel in (grid._forward_rows, grid._forward_grid_sample):
        grid.zero_grad()
        features = kernel(points)
        (features * upstream).sum().backward()
        gradients.append((features.detach(), [p.grad.clone() for p in grid.parameters()]))
    (rows, row_grads), (sampled, sampled_grads) = gradients
    assert torch.allclose(rows, sampled, atol=1e-12)
    assert rows[4].abs().max() == 0  # a cell and more beyond every face
    for got, expected in zip(row_grads, sampled_grads):
        assert torch.allclose(got, expected, atol=1e-12)


def test_the_row_tables_kept_for_rendering_follow_the_weights():
    torch.manual_seed(4)
    grid = VectorMatrixGrid(channels=3, vertices=6)
    points = torch.rand(50, 3) * 2 - 1
    with torch.no_grad():
        before = grid(points)
        grid.planes[1].mul_(2.0)  # an optimiser step: in place
        after = grid(points)
        assert torch.allclose(after, grid._forward_grid_sample(points), atol=1e-6)
        assert not torch.allclose(after, before)
    grid.resize(8)  # new parameters
    with torch.no_grad():
        assert torch.allclose(grid(points), grid._forward_grid_sample(points), atol=1e-6)


def test_dense_sum_equals_the_interpolated_feature_sum_at_vertices():
    torch.manual_seed(1)
    vertices = torch.tensor([7, 5, 6])
    grid = VectorMatrixGrid(channels=4, vertices=tuple(vertices.tolist())).double()
    volume = grid.dense_sum()  # laid out (z, y, x), as grid_sample reads volumes
    assert volume.shape == (6, 5, 7)
    index = (torch.rand(30, 3) * vertices).long()
    points = index.double() / (vertices - 1) * 2 - 1
    assert torch.allclose(grid(points).sum(dim=-1), volume[index[:, 2], index[:, 1], index[:, 0]], atol=1e-12)


def _linear_grid() -> VectorMatrixGrid:
    """A grid of 5 vertices a side whose volume is linear per axis: any resampling keeps it."""
    grid = VectorMatrixGrid(channels=2, vertices=5).double()
    with torch.no_grad():
        axis = torch.linspace(-1, 1, 5, dtype=torch.float64)
        for plane in grid.planes:
            plane[:] = (axis[:, None] + 2 * axis[None, :])[None, None]
        for line in grid.lines:
            line[:] = (1 + 0.5 * axis)[None, None, :, None]
    return grid


def test_resize_keeps_the_represented_volume():
    torch.manual_seed(2)
    grid = _linear_grid()
    points = torch.rand(50, 3, dtype=torch.float64) * 2 - 1
    before = grid(points)
    grid.resize((11, 9, 7))
    assert grid.planes[0].shape[-2:] == (11, 9) and grid.lines[0].shape[-2] == 7 and grid.lines[2].shape[-2] == 11
    assert torch.allclose(grid(points), before, atol=1e-12)


def test_resizing_to_a_part_of_the_grid_keeps_the_volume_there():
    """A volume linear per axis survives resampling exactly: the part of it read at the same
    world points after the part became the whole grid."""
    grid = _linear_grid()
    lower, upper = torch.tensor([-0.6, -0.2, 0.1], dtype=torch.float64), torch.tensor([0.5, 0.9, 0.7], dtype=torch.float64)
    points = lower + torch.rand(60, 3, dtype=torch.float64) * (upper - lower)
    before = grid(points)
    grid.resize((13, 12, 8), tuple(lower.tolist()), tuple(upper.tolist()))
    assert grid.vertices == (13, 12, 8) and grid.planes[1].shape[-2:] == (13, 8) and grid.lines[0].shape[-2] == 8
    assert torch.allclose(grid((points - lower) / (upper - lower) * 2 - 1), before, atol=1e-12)


BLOB = ((0.1, 0.6), (-0.5, 0.0), (-0.3, 0.4))


def _blob_model(config=None, blob=BLOB) -> GridModel:
    """A fast model over [-1, 1]³ whose density lies only in ``blob`` (world ranges; by default
    x ∈ [0.1, 0.6], y ∈ [-0.5, 0], z ∈ [-0.3, 0.4]): every factor is zero outside that part of
    its axes, so the 2-unit box is mostly empty, as nerf_synthetic's 3-unit box is around its
    objects."""
    torch.manual_seed(5)
    model = GridModel(config or dataclasses.replace(PRESETS["fast"], fit_box_at=1), BOX)
    _fill_blob(model, blob)
    return model


def _fill_blob(model: GridModel, blob) -> None:
    """The model's density made to lie only in ``blob`` (world ranges), over its box as it is."""
    field = model.field
    inside = []
    for n, (lo, hi), low, high in zip(field.vertices, blob, field.box_min.tolist(), field.box_max.tolist()):
        world = torch.linspace(low, high, n)
        inside.append((world >= lo) & (world <= hi))
    grid = field.density_grid
    with torch.no_grad():
        for ((a, b), c), plane, line in zip((((0, 1), 2), ((0, 2), 1), ((1, 2), 0)), grid.planes, grid.lines):
            plane.uniform_(0.5, 1.5).mul_((inside[a][:, None] & inside[b][None, :]).float())
            line.uniform_(0.5, 1.5).mul_(inside[c][:, None].float())
        grid.planes[0].mul_(9.0)
    model.update_occupancy()
    return model


def _rays_at(model_box: SceneBounds, count: int, seed: int) -> tuple[torch.Tensor, ...]:
    from nerf_backend.core.cameras import ray_box_intersection

    generator = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1) * 3.0
    targets = torch.rand(count, 3, generator=generator) * 1.2 + torch.tensor([-0.25, -0.85, -0.55])
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    near, far, _ = ray_box_intersection(origins, directions, torch.tensor(model_box.box_min),
                                        torch.tensor(model_box.box_max))
    return origins, directions, near, far


def test_fitting_the_box_narrows_the_field_to_its_density_and_keeps_the_image():
    model = _blob_model()
    rays = _rays_at(BOX, 2000, seed=1)
    with torch.no_grad():
        before = model.eval()(*rays)[0]
    cells_before = math.prod(model.field.occupancy_cells())
    assert model.train().before_step(16, 1) is True and model.box_fitted  # at fit_box_at, once
    assert model.before_step(32, 2) is False
    box_min, box_max = model.field.box_min, model.field.box_max
    # The density's part of the box, two cells wider each side (cells of 2/47).
    margin = 2 * 2 / 47 + 2 / 47 + 1e-6
    assert (box_min <= torch.tensor([0.1, -0.5, -0.3])).all() and (box_max >= torch.tensor([0.6, 0.0, 0.4])).all()
    assert (box_min >= torch.tensor([0.1, -0.5, -0.3]) - margin).all()
    assert (box_max <= torch.tensor([0.6, 0.0, 0.4]) + margin).all()
    # The cells keep their count and shrink with the box; the march follows them.
    assert abs(math.prod(model.field.occupancy_cells()) / cells_before - 1) < 0.1
    assert model.occupancy.box_max.tolist() == box_max.tolist()
    with torch.no_grad():
        after = model.eval()(*rays)[0]
    assert 0.2 < float(before.opacity.mean()) < 0.9  # rays through the blob and beside it
    # Resampled finer and marched in finer steps: the same image but where a ray grazes the
    # blob's sharp edge, which the coarser steps miss (measured: mean 0.0020, 98 % of rays
    # within 0.0003, the worst ray 0.44).
    change = (after.rgb - before.rgb).abs().amax(dim=-1)
    assert float(change.mean()) < 0.005 and float(change.quantile(0.98)) < 0.01
    assert "box fitted" in model.take_note()


def test_the_fitted_bounds_leave_out_floaters_but_keep_every_large_piece():
    grid = OccupancyGrid(torch.zeros(3), torch.ones(3), cells=40)
    grid.occupied.zero_()
    grid.occupied[10:20, 12:30, 5:15] = True  # the scene: 1 800 cells
    grid.occupied[25:29, 12:16, 20:23] = True  # a second object apart from it: 48 cells
    specks = torch.randint(0, 40, (200, 3), generator=torch.Generator().manual_seed(0))
    specks = specks[(specks[:, 2] >= 30)]  # floaters above both, one cell each
    grid.occupied[specks[:, 0], specks[:, 1], specks[:, 2]] = True
    everything = grid.occupied_bounds(0)
    assert everything.box_max[2] == 1.0  # the floaters reach the top
    bounds = grid.occupied_bounds(0, min_part=0.01)
    assert [round(v * 40) for v in bounds.box_min] == [10, 12, 5]
    assert [round(v * 40) for v in bounds.box_max] == [29, 30, 23]


def test_a_fitted_box_survives_a_checkpoint_and_a_full_box_is_left_alone():
    model = _blob_model()
    model.fit_box()
    rays = _rays_at(BOX, 500, seed=2)
    fresh = GridModel(dataclasses.replace(PRESETS["fast"], fit_box_at=1), BOX)
    fresh.restore(model.state_dict())
    assert fresh.box_fitted and fresh.field.vertices == model.field.vertices
    with torch.no_grad():
        assert torch.equal(fresh.eval()(*rays)[0].rgb, model.eval()(*rays)[0].rgb)
    assert fresh.train().before_step(16, 1) is False  # fitted already: not again
    # Density everywhere: the box would keep all of its volume, so it stays.
    full = GridModel(dataclasses.replace(PRESETS["fast"], fit_box_at=1), BOX)
    assert full.fit_box() is False and not full.box_fitted


def test_a_box_not_narrowed_at_first_is_tried_again_after_the_next_growth():
    """At ``fit_box_at`` a young field's haze can fill the box (it stays: "box kept"); once the
    density has gathered into the scene, the next growth of the grid tries again, and then the
    box narrows. No retry between growths."""
    model = _blob_model()
    grid = model.field.density_grid
    blob = [parameter.detach().clone() for parameter in grid.parameters()]
    with torch.no_grad():
        for parameter in grid.parameters():
            parameter.uniform_(0.5, 1.5)
        grid.planes[0].mul_(9.0)  # density everywhere
    model.update_occupancy()
    assert model.train().before_step(16, 1) is False and not model.box_fitted
    assert "box kept" in model.take_note()
    with torch.no_grad():
        for parameter, kept in zip(grid.parameters(), blob):
            parameter.copy_(kept)  # the density gathered into the blob
    model.update_occupancy()
    assert model.before_step(17, 2) is False and not model.box_fitted  # no growth yet: no retry
    growth = PRESETS["fast"].grid.upsample_iterations[0]
    assert model.before_step(18, growth) is True and not model.box_fitted  # the grid grew
    assert model.before_step(19, growth + 1) is True and model.box_fitted
    assert "box fitted" in model.take_note()


def test_a_fitted_box_is_fitted_again_after_a_growth_once_the_haze_around_the_scene_has_gone():
    """The first fit meets a young field whose haze spans more than the scene; the step after
    each later growth fits the box again from the finer grid's occupancy, with as many cells,
    so they shrink with it (lego at 800×800: 34 % of the guessed box, then 21 % and 18 %). A
    box that would keep more than ``REFIT_MAX_KEPT`` of itself is left as it is."""
    model = _blob_model(blob=((-0.4, 0.8), (-0.9, 0.3), (-0.6, 0.7)))  # the scene and its haze
    assert model.train().before_step(16, 1) is True and model.box_fitted
    wide, cells = model.field.extent, math.prod(model.field.occupancy_cells())
    assert "box fitted to" in model.take_note()
    _fill_blob(model, BLOB)  # the haze gone
    model.update_occupancy()
    growth = PRESETS["fast"].grid.upsample_iterations[0]
    assert model.before_step(17, growth) is True and model.field.extent == wide  # grown, the box as it was
    grown_cells = math.prod(model.field.occupancy_cells())
    assert grown_cells > 2 * cells
    # Two cells of margin each side, a cell's rounding and the density's spread to the next vertex.
    margin = 4 * max(side / count for side, count in zip(wide, model.field.occupancy_cells())) + 1e-6
    assert model.before_step(18, growth + 1) is True  # and fitted again
    assert "box fitted again" in model.take_note()
    box_min, box_max = model.field.box_min, model.field.box_max
    blob_min, blob_max = torch.tensor([r[0] for r in BLOB]), torch.tensor([r[1] for r in BLOB])
    assert (box_min <= blob_min).all() and (box_max >= blob_max).all()
    assert (box_min >= blob_min - margin).all() and (box_max <= blob_max + margin).all()
    assert math.prod(model.field.extent) < 0.3 * math.prod(wide)
    assert abs(math.prod(model.field.occupancy_cells()) / grown_cells - 1) < 0.1  # the cells shrank with it
    narrowed = model.field.extent
    assert model.before_step(19, growth + 2) is False  # no growth: no fit
    _fill_blob(model, ((-1.0, 1.0),) * 3)  # density over the whole of the narrowed box
    model.update_occupancy()
    assert model.fit_box() is False and model.field.extent == narrowed  # it would keep all of itself
    assert model.take_note() is None  # said only of the first fit


def test_a_large_grid_refreshes_its_occupancy_less_often():
    """The refresh reads every vertex: a 255³ grid refreshes every 67 steps, not 16, so that
    it stays near 5 % of a step; a grid of up to 2 M cells keeps occupancy_every."""
    model = GridModel(PRESETS["fast"], BOX)
    assert model.occupancy_refresh_every() == PRESETS["fast"].occupancy_every == 16
    model.resize((256, 256, 256))
    assert model.occupancy_refresh_every() == 67
    refreshed = []
    model.update_occupancy = lambda: refreshed.append(True)
    for iteration in range(16, 16 + 134):
        model.before_step(iteration, 0)
    assert len(refreshed) == 2


FLAT_BOX = SceneBounds((-1.0, -1.0, -0.2), (1.0, 1.0, 0.2))


@pytest.mark.parametrize("box", [BOX, FLAT_BOX], ids=["cube", "flat"])
def test_occupancy_grid_never_skips_a_cell_that_holds_density(box):
    """Random fields: every point whose density exceeds the threshold lies in an occupied
    cell, because the bound at a cell's corners is exact for the grid field (also with a
    vertex count of its own on each axis of a flat box)."""
    config = PRESETS["fast"]
    low, high = torch.tensor(box.box_min), torch.tensor(box.box_max)
    for seed in range(3):
        torch.manual_seed(seed)
        model = GridModel(config, box)
        with torch.no_grad():  # a field with structure: some dense blobs, mostly empty
            for plane in model.field.density_grid.planes:
                plane.normal_(0.0, 2.0)
        model.update_occupancy()
        density_threshold = min(model.density_threshold, float(model.field.vertex_density().mean()))
        points = torch.rand(200_000, 3) * (high - low) + low
        density = model.field.density(points)
        dense_points = points[density > density_threshold]
        assert dense_points.shape[0] > 100, "the test field must have dense regions"
        assert model.occupancy.query(dense_points).all()
        assert 0.0 < model.occupancy.occupied_fraction < 1.0


def test_a_flat_box_gets_cubic_cells():
    model = GridModel(PRESETS["fast"], FLAT_BOX)
    assert model.field.vertices == (48, 48, 10)  # 48 along the long sides: cells 2/47 by 0.4/9
    cell = [side / (n - 1) for side, n in zip((2.0, 2.0, 0.4), model.field.vertices)]
    assert max(cell) / min(cell) < 1.05
    assert model.occupancy.occupied.shape == (47, 47, 9)


def test_occupancy_query_outside_the_box_is_empty():
    grid = OccupancyGrid(torch.tensor([-1.0] * 3), torch.tensor([1.0] * 3), cells=4)
    assert not grid.query(torch.tensor([[1.5, 0.0, 0.0], [0.0, -2.0, 0.0]])).any()
    assert grid.query(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])).all()


class _Ball(torch.nn.Module):
    """An analytic field both models can render: a sphere of constant density and colour."""

    density_value = 30.0
    colour_value = torch.tensor([0.9, 0.3, 0.1])

    def density(self, x):
        return torch.where(x.norm(dim=-1) < 0.5, self.density_value, 0.0)

    def density_along(self, x, d):
        return self.density(x)

    def colour(self, x, d):
        return self.colour_value.expand(x.shape[0], 3)

    def forward(self, x, d):
        return self.density(x), self.colour(x, d)

    def shade_fn(self):  # its samples carry colours (no deferred colour)
        return None

    # The grid model's no-gradient reads go through a density volume; the ball has none.
    def density_volume(self):
        return None

    def density_from_volume(self, volume, x, directions=None):
        return self.density(x)


def test_fast_and_paper_rendering_agree_on_an_analytic_field():
    torch.manual_seed(0)
    origins = torch.tensor([[0.0, -3.0, 0.0]]).repeat(64, 1)
    targets = torch.rand(64, 3) * 1.2 - 0.6
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    # Closed form: a chord of length c through the ball has opacity 1 - exp(-σ c).
    closest = (origins + directions * (-(origins * directions).sum(-1, keepdim=True))).norm(dim=-1)
    chord = 2 * torch.sqrt((0.25 - closest**2).clamp_min(0))
    opacity = 1 - torch.exp(-_Ball.density_value * chord)
    expected = opacity[:, None] * _Ball.colour_value + (1 - opacity[:, None])

    paper = NerfModel(PRESETS["paper"]).eval()
    paper.coarse, paper.fine = _Ball(), _Ball()
    t_near, t_far = torch.full((64,), 2.0), torch.full((64,), 4.0)
    paper_rgb = paper(origins, directions, t_near, t_far)[-1].rgb

    fast = GridModel(PRESETS["fast"], BOX).eval()
    fast.field = _Ball()
    from nerf_backend.core.cameras import ray_box_intersection
    near, far, _ = ray_box_intersection(origins, directions, torch.tensor(BOX.box_min), torch.tensor(BOX.box_max))
    fast_rgb = fast(origins, directions, near, far)[-1].rgb
    # Both discretise the same integral; at these step sizes they agree with the closed form
    # to 0.03 (a step cutting the sphere's edge) and with each other.
    assert (paper_rgb - expected).abs().max() < 0.03
    assert (fast_rgb - expected).abs().max() < 0.03
    assert (fast_rgb - paper_rgb).abs().max() < 0.03


def test_coarse_to_fine_schedule():
    model = GridModel(PRESETS["fast"], BOX)
    grid = PRESETS["fast"].grid
    assert model.field.resolution == grid.initial_resolution
    resolutions = [model.field.resolution_after(i) for i in (0, grid.upsample_iterations[0], 10**6)]
    assert resolutions[0] < resolutions[1] < resolutions[2] == grid.resolution
    assert model.before_step(0, grid.upsample_iterations[0]) is True
    assert model.field.resolution == resolutions[1]
    assert model.occupancy.cells == (resolutions[1] - 1,) * 3


def _solid_grid_model(render_alpha_threshold: float = 0.0) -> GridModel:
    """A fast model whose random grids hold dense blobs and empty space, occupancy updated.
    Rendering skips no more than training unless given a ``render_alpha_threshold``."""
    torch.manual_seed(3)
    model = GridModel(dataclasses.replace(PRESETS["fast"], render_alpha_threshold=render_alpha_threshold), BOX)
    vertices = model.field.vertices
    model.resize((5, 5, 5))  # random values on a coarse grid, interpolated up: smooth blobs
    with torch.no_grad():
        for parameter in model.field.density_grid.parameters():
            parameter.normal_(0.0, 1.4)
    model.resize(vertices)
    model.update_occupancy()
    assert 0.05 < model.occupancy.occupied_fraction < 0.95  # both kinds of space present
    return model.eval()


def test_density_volume_reads_the_same_density_as_the_grids():
    model = _solid_grid_model()
    points = torch.rand(5000, 3) * (torch.tensor(BOX.box_max) - torch.tensor(BOX.box_min)) + torch.tensor(BOX.box_min)
    direct = model.field.density(points)
    from_volume = model.field.density_from_volume(model.field.density_volume(), points)
    # Trilinear of the vertex products is exactly the factorised value; float32 rounding only.
    assert torch.allclose(from_volume, direct, rtol=1e-4, atol=1e-4)


def test_inference_render_matches_the_training_march():
    """Without gradients the model marches only occupied spans, stops opaque rays, reads
    density from the dense volume and leaves the faintest weight uncoloured; the image must
    equal the full march to the bounds of those shortcuts."""
    model = _solid_grid_model()
    from nerf_backend.core.cameras import ray_box_intersection

    torch.manual_seed(4)
    origins = torch.nn.functional.normalize(torch.randn(3000, 3), dim=-1) * 4.0
    targets = torch.rand(3000, 3) * 2.0 - 1.0
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    near, far, _ = ray_box_intersection(origins, directions, torch.tensor(BOX.box_min), torch.tensor(BOX.box_max))
    with torch.enable_grad():
        full = model(origins, directions, near, far)[0]
    with torch.no_grad():
        early = model(origins, directions, near, far)[0]
    assert early.weights is None and full.weights is not None  # the two paths really differ
    opaque = full.opacity > 0.9999
    assert 0 < opaque.sum() < len(opaque)  # some rays stop early, some pass through
    # A stopped ray loses at most its remaining transmittance (1e-4) of colour and opacity.
    tolerance = GridModel.OPAQUE_TRANSMITTANCE + 1e-5
    # Colour also leaves up to SKIPPED_WEIGHT of a ray's faintest weight to its mean colour.
    assert (early.rgb - full.rgb).abs().max() < tolerance + SKIPPED_WEIGHT
    assert (early.opacity - full.opacity).abs().max() < tolerance
    assert (early.depth - full.depth).abs().max() < tolerance * float(far.max()) + 1e-4


def test_rendering_skips_faint_cells_within_the_bound_they_set():
    """Rendering drops the training grid's cells whose largest density cannot reach
    ``render_alpha_threshold`` in one step (the grid field's cell maxima are exact). Each
    dropped step would have taken at most that alpha, so a ray's opacity and colour move by
    at most (its steps in dropped cells) × the threshold, over the early-stop tolerances."""
    from nerf_backend.core.cameras import ray_box_intersection
    from nerf_backend.model_components.marcher import march_edges
    from nerf_backend.model_components.samplers import interval_midpoints

    threshold = 1e-2
    model = _solid_grid_model(render_alpha_threshold=threshold)
    saved = set(model.state_dict())
    kept = model.render_occupancy().occupied
    assert set(model.state_dict()) == saved  # a derived grid: no part of the checkpoint
    dropped = model.occupancy.occupied & ~kept
    assert not (kept & ~model.occupancy.occupied).any()  # never a cell training skips
    assert dropped.sum() > 0.05 * model.occupancy.occupied.sum() and kept.any()
    torch.manual_seed(8)
    origins = torch.nn.functional.normalize(torch.randn(3000, 3), dim=-1) * 4.0
    directions = torch.nn.functional.normalize(torch.rand(3000, 3) * 2.0 - 1.0 - origins, dim=-1)
    near, far, _ = ray_box_intersection(origins, directions, torch.tensor(BOX.box_min), torch.tensor(BOX.box_max))
    with torch.enable_grad():
        full = model(origins, directions, near, far)[0]
    with torch.no_grad():
        pruned = model(origins, directions, near, far)[0]
    # The march's steps whose midpoints lie in dropped cells, per ray.
    t_edges = march_edges(near, far, model.step, torch.zeros(len(origins), 1), 0, model.samples_per_ray)
    t_mid = interval_midpoints(t_edges)
    lengths = t_edges[:, 1:] - t_edges[:, :-1]
    points = origins[:, None] + directions[:, None] * t_mid[..., None]
    grid = OccupancyGrid(model.occupancy.box_min, model.occupancy.box_max, model.occupancy.cells)
    grid.occupied.copy_(dropped)
    in_dropped = (grid.query(points.view(-1, 3)).view(lengths.shape) & (lengths > 0)).sum(dim=1)
    bound = in_dropped * threshold + GridModel.OPAQUE_TRANSMITTANCE + 1e-5
    assert (in_dropped > 0).float().mean() > 0.2 and (bound < 0.5).float().mean() > 0.5  # the bound says something
    assert ((pruned.opacity - full.opacity).abs() <= bound).all()
    assert ((pruned.rgb - full.rgb).abs().amax(dim=1) <= bound + SKIPPED_WEIGHT).all()
    assert (pruned.opacity - full.opacity).abs().max() > 1e-4  # and the skipping happened


def test_a_young_faint_field_still_renders_its_denser_part():
    """A new field is faint everywhere, far below the render threshold: rendering then keeps
    the cells above the cells' mean instead of dropping everything (nerfacc's rule)."""
    torch.manual_seed(9)
    model = GridModel(PRESETS["fast"], BOX)
    model.update_occupancy()
    cell_max = model.field.cell_max_density()
    assert float(cell_max.max()) < model.render_density_threshold
    kept = model.render_occupancy().occupied
    assert torch.equal(kept, (cell_max > cell_max.mean()) & model.occupancy.occupied) and kept.any()


def test_a_hash_field_renders_with_the_training_grid_until_it_has_an_estimate():
    from nerf_backend.models.registry import HashModel

    model = HashModel(PRESETS["hash"], BOX)
    assert model.field.cell_max_density() is None
    assert model.render_occupancy() is model.occupancy
    model.update_occupancy()
    assert model.render_occupancy() is not model.occupancy


def test_widened_cells_equal_a_max_pool_over_the_cube():
    """The skip grid's widening against its definition: the maximum over the (2r+1)³ cube
    around each cell, here with max_pool3d, on a box that is not a cube and radii up to
    larger than a side."""
    from nerf_backend.model_components.occupancy import widened

    torch.manual_seed(10)
    cells = torch.rand(23, 9, 4) < 0.01
    cells[22, 8, 3] = True  # a corner
    for radius in (1, 2, 4, 6):
        width = 2 * radius + 1
        reference = torch.nn.functional.max_pool3d(cells.float()[None, None], width, stride=1, padding=radius)
        assert torch.equal(widened(cells, radius), reference[0, 0] > 0)


def test_occupied_spans_cover_every_occupied_step():
    """The skip pass is conservative: every march step whose midpoint lies in an occupied
    fine cell is inside a span ``occupied_spans`` returns, on a scattered occupancy."""
    from nerf_backend.core.cameras import ray_box_intersection
    from nerf_backend.model_components.marcher import occupied_spans

    torch.manual_seed(5)
    box_min, box_max = torch.tensor([-1.0, -0.5, -0.25]), torch.tensor([1.0, 0.5, 0.25])  # not a cube
    grid = OccupancyGrid(box_min, box_max, (64, 32, 16))
    grid.occupied.copy_(torch.rand(64, 32, 16) < 0.002)  # scattered specks: most skip cells empty
    origins = torch.nn.functional.normalize(torch.randn(4000, 3), dim=-1) * 3.0
    directions = torch.nn.functional.normalize(torch.rand(4000, 3) * (box_max - box_min) + box_min - origins, dim=-1)
    near, far, _ = ray_box_intersection(origins, directions, box_min, box_max)
    step = 1.0 / 32 * 0.7
    steps = math.ceil(float((box_max - box_min).norm()) / step) + 1
    ray, first, span = occupied_spans(grid, origins, directions, near, far, step, steps)
    assert span > 1 and len(ray) < 0.5 * len(origins) * steps / span  # it does skip
    covered = torch.zeros(len(origins), steps + span, dtype=torch.bool)
    for offset in range(span):
        covered[ray, first + offset] = True
    u = torch.arange(steps - 1)
    t_lo = torch.minimum(near[:, None] + u * step, far[:, None])
    t_hi = torch.minimum(t_lo + step, far[:, None])
    mid = origins[:, None] + directions[:, None] * (0.5 * (t_lo + t_hi))[..., None]
    occupied = grid.query(mid.view(-1, 3)).view(len(origins), -1) & (t_hi > t_lo)
    assert occupied.sum() > 100
    assert not (occupied & ~covered[:, :steps - 1]).any()


def test_inference_skips_empty_space_and_still_matches_the_training_march():
    """Occupancy restricted to a corner: most spans are skipped without a fine step, and the
    image still equals the full march to the early-stop bound."""
    model = _solid_grid_model()
    from nerf_backend.core.cameras import ray_box_intersection
    from nerf_backend.model_components.marcher import occupied_spans

    corner = torch.zeros_like(model.occupancy.occupied)
    corner[: corner.shape[0] // 3, : corner.shape[1] // 2] = True
    model.occupancy.occupied &= corner
    torch.manual_seed(6)
    origins = torch.nn.functional.normalize(torch.randn(3000, 3), dim=-1) * 4.0
    directions = torch.nn.functional.normalize(torch.rand(3000, 3) * 2.0 - 1.0 - origins, dim=-1)
    near, far, _ = ray_box_intersection(origins, directions, torch.tensor(BOX.box_min), torch.tensor(BOX.box_max))
    ray, _, span = occupied_spans(model.occupancy, origins, directions, near, far, model.step, model.samples_per_ray)
    assert len(ray) * span < 0.6 * int((far > near).sum()) * model.samples_per_ray
    with torch.enable_grad():
        full = model(origins, directions, near, far)[0]
    with torch.no_grad():
        early = model(origins, directions, near, far)[0]
    assert 0 < (full.opacity > 0.5).sum() < len(origins)
    tolerance = GridModel.OPAQUE_TRANSMITTANCE + 1e-5
    # Colour also leaves up to SKIPPED_WEIGHT of a ray's faintest weight to its mean colour.
    assert (early.rgb - full.rgb).abs().max() < tolerance + SKIPPED_WEIGHT
    assert (early.opacity - full.opacity).abs().max() < tolerance
    assert (early.depth - full.depth).abs().max() < tolerance * float(far.max()) + 1e-4


def test_occupancy_along_rays_equals_the_query_of_world_points():
    """The inference march asks in cell units along each ray; it must say what ``query``
    says of the same world points, boundaries aside (the two round differently there)."""
    torch.manual_seed(7)
    box_min, box_max = torch.tensor([-1.0, -0.5, -0.25]), torch.tensor([1.0, 0.5, 0.25])
    grid = OccupancyGrid(box_min, box_max, (40, 20, 10))
    grid.occupied.copy_(torch.rand(40, 20, 10) < 0.3)
    origins = torch.randn(500, 3) * 2.0
    directions = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    t = torch.rand(500, 64) * 5.0
    along = grid.occupied_along(origins, directions, t)
    points = (origins[:, None] + directions[:, None] * t[..., None]).view(-1, 3)
    direct = grid.query(points).view(500, 64)
    assert along.any() and (~along).any()
    units = ((points - box_min) / (box_max - box_min) * torch.tensor([40.0, 20.0, 10.0])).view(500, 64, 3)
    near_boundary = ((units - units.round()).abs() < 1e-4).any(dim=-1)
    assert not (along != direct)[~near_boundary].any()


def test_render_caches_follow_weights_swapped_as_module_to_swaps_them():
    """``module.to(device)`` keeps each parameter object and swaps its storage; the density
    volume, the render grid and the row tables kept for rendering must follow (keyed on the
    storage and device, not on the parameter's identity; a GPU run once rendered with the
    CPU's volume)."""
    model = _solid_grid_model()
    from nerf_backend.core.cameras import ray_box_intersection

    origins = torch.tensor([[0.0, -4.0, 0.0]]).repeat(200, 1)
    directions = torch.nn.functional.normalize(torch.rand(200, 3) * 0.4 - 0.2 + torch.tensor([0.0, 1.0, 0.0]), dim=-1)
    near, far, _ = ray_box_intersection(origins, directions, torch.tensor(BOX.box_min), torch.tensor(BOX.box_max))
    with torch.no_grad():
        before = model(origins, directions, near, far)[0]
        assert before.opacity.max() > 0.5  # the blobs are seen
        for parameter in model.field.density_grid.parameters():
            parameter.data = torch.zeros_like(parameter.data)  # only the faint shift left, as ``to`` would swap it
        after = model(origins, directions, near, far)[0]
    assert after.opacity.max() < 0.01  # what softplus(shift) leaves over the box


@pytest.mark.parametrize("preset, group, settings", [
    ("fast", "grid", {}), ("fast", "grid", {"view_dependent": False}),
    ("surface", "surface", {}), ("surface", "surface", {"normal_input": True}),
    ("surface", "surface", {"reflected_directions": True}),
])
def test_ray_colour_is_each_samples_colour_along_its_ray(preset, group, settings, monkeypatch):
    """Inference colours packed samples with ``field.ray_colour(directions)``, which may do a
    ray's share of the work once a ray (the grid appearance's direction columns): it must give
    ``colour(x, directions[ray])`` to float32 rounding, whatever the field's colour inputs."""
    from nerf_backend.models.registry import build_model

    torch.manual_seed(5)
    config = PRESETS[preset]
    config = config.with_settings(**{group: dataclasses.replace(getattr(config, group), **settings)})
    field = build_model(config, BOX).field.eval()
    with torch.no_grad():
        for parameter in field.parameters():
            parameter.normal_(0.0, 0.3)
        directions = torch.nn.functional.normalize(torch.randn(300, 3), dim=-1)
        ray = torch.randint(0, 300, (5000,))
        points = (torch.rand(5000, 3) * 2 - 1) * 0.9
        expected = field.colour(points, directions.index_select(0, ray))
        actual = field.ray_colour(directions)(points, ray)
    assert actual.shape == (5000, 3) and actual.dtype == torch.float32
    assert torch.allclose(actual, expected, atol=1e-6, rtol=0)
    assert float(expected.std()) > 0.05  # random weights: colours that differ, not a constant
    # PyTorch's colour in bfloat16 (where the compiled pass does not apply, on a CPU whose
    # bfloat16 products are faster: devices.colour_network_dtype): the products round to 8 bits
    # of mantissa: colours within 2 % of their range, 0.3 % on average.
    import nerf_backend.fields.grid_appearance as grid_appearance
    monkeypatch.setattr(grid_appearance, "compiled_ray_colour", lambda field, directions, dtype: None)
    with torch.no_grad():
        rounded = field.ray_colour(directions, torch.bfloat16)(points, ray)
    assert rounded.dtype == torch.float32
    assert float((rounded - expected).abs().max()) < 2e-2 and float((rounded - expected).abs().mean()) < 3e-3


def test_the_last_growth_waits_for_the_steps_a_budget_leaves():
    """grid.last_growth_min_steps: the growth to the final size happens only with that many
    steps left (said once when held back); the earlier growths, and a run without a budget
    (steps_left None), grow as scheduled."""
    grid = dataclasses.replace(PRESETS["fast"].grid, last_growth_min_steps=1500)
    config = PRESETS["fast"].with_settings(grid=grid)
    first, *_, last = grid.upsample_iterations
    model = GridModel(config, BOX)
    assert model.before_step(0, first, steps_left=10.0) is True  # not the last growth: it grows
    penultimate = model.field.resolution_after(last - 1)
    model.field.resize(model.field.vertices_at(penultimate))
    assert model.before_step(0, last, steps_left=1499.0) is False
    assert model.field.resolution == penultimate < grid.resolution
    note = model.take_note()
    assert f"grid kept at {penultimate} vertices a side, not grown to {grid.resolution}" in note
    assert "about 1499 steps are left" in note and "waits for 1500" in note
    assert model.before_step(0, last + 50, steps_left=1400.0) is False and model.take_note() is None  # said once
    assert model.before_step(0, last + 60, steps_left=1500.0) is True  # enough left: it grows
    assert model.field.resolution == grid.resolution
    unbudgeted = GridModel(config, BOX)
    unbudgeted.field.resize(unbudgeted.field.vertices_at(penultimate))
    assert unbudgeted.before_step(0, last, steps_left=None) is True and unbudgeted.take_note() is None
