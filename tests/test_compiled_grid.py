"""The compiled read of the factorised grids (kernels/vm_grid.c through
field_components/compiled_grid.py) against PyTorch's, which is the reference: the same
features and the same gradients, within float32 rounding (1e-5 relative to the largest value,
stated per check), on small grids of uneven sizes, with points inside, on the border of and
outside the grid."""

from __future__ import annotations

import pytest
import torch

from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.field_components import compiled_grid
from nerf_backend.field_components.grid_encodings import VectorMatrixGrid
from nerf_backend.fields.grid_field import GridField, GridFieldConfig


@pytest.fixture(scope="module", autouse=True)
def library():
    found = compiled_grid.compiled_grid_library()
    if found is None:
        pytest.skip("no C compiler here: the compiled grid is not built (the PyTorch path trains)")
    return found


def _grids(seed: int = 0) -> list[VectorMatrixGrid]:
    torch.manual_seed(seed)
    return [VectorMatrixGrid(8, (9, 7, 5)), VectorMatrixGrid(24, (6, 11, 13))]


def _points(count: int, seed: int, spread: float = 1.1) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return (torch.rand(count, 3, generator=generator) * 2 - 1) * spread


def _reference(grids, x):
    return torch.cat([grid._forward_rows(x) for grid in grids], dim=1)


def _close(a: torch.Tensor, b: torch.Tensor, relative: float = 1e-5) -> bool:
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max()) <= relative * max(1.0, float(b.abs().max()))


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_features_and_gradients_match_pytorch(threads, monkeypatch):
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    grids = _grids()
    x = _points(3000, seed=1)  # 10 % of them outside [-1, 1]: read as zero padding fades
    weights = torch.randn(3000, sum(g.out_dims for g in grids), generator=torch.Generator().manual_seed(2))
    reference = _reference(grids, x)
    (reference * weights).sum().backward()
    expected = [p.grad.clone() for g in grids for p in g.parameters()]
    for grid in grids:
        grid.zero_grad(set_to_none=True)
    compiled = compiled_grid.read_grids(grids, x)
    assert compiled is not None and _close(compiled, reference)
    (compiled * weights).sum().backward()
    for want, parameter in zip(expected, [p for g in grids for p in g.parameters()]):
        assert parameter.grad.shape == parameter.shape and _close(parameter.grad, want)


# Vertices along x that leave each of the kernel's paths a remainder: runs of 32, single
# vectors of 8, and single vertices (5: none but those; 70: 2 runs, no vector, 6 single).
@pytest.mark.parametrize("channels, vertices", [(16, (5, 4, 3)), (8, (70, 9, 11)), (12, (45, 13, 17)),
                                                (24, (33, 2, 40))])
@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_dense_sum_equals_the_three_matrix_products(channels, vertices, threads, monkeypatch):
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    torch.manual_seed(channels)
    grid = VectorMatrixGrid(channels, vertices, init_scale=1.0)
    with torch.no_grad():
        compiled = compiled_grid.dense_sum(grid)
        reference = grid._dense_sum_float32()
    nx, ny, nz = vertices
    assert compiled is not None and compiled.shape == reference.shape == (nz, ny, nx)
    # The same 3·C products per vertex in another order: float32 rounding only.
    assert _close(compiled, reference)
    assert torch.equal(grid.dense_sum(), compiled)  # what the grid gives outside autograd


def test_a_dense_sum_wanting_gradients_is_left_to_pytorch():
    grid = VectorMatrixGrid(8, (9, 7, 5))
    assert compiled_grid.dense_sum(grid) is None  # its parameters want gradients, and autograd is on
    with torch.no_grad():
        assert compiled_grid.dense_sum(grid) is not None


def test_a_grid_of_other_channel_counts_reads_through_pytorch():
    grid = VectorMatrixGrid(3, 6)
    assert compiled_grid.read_grids([grid], _points(10, seed=3)) is None
    assert grid(_points(10, seed=3)).shape == (10, 9)


def test_points_needing_gradients_read_through_pytorch():
    x = _points(10, seed=4).requires_grad_()
    assert compiled_grid.read_grids(_grids(), x) is None


def test_nan_points_read_zero_and_leave_the_others_and_the_gradient_finite():
    grids = _grids()
    x = _points(200, seed=5)
    x[3] = float("nan")
    x[7, 1] = float("inf")
    compiled = compiled_grid.read_grids(grids, x)
    finite = torch.ones(200, dtype=torch.bool)
    finite[[3, 7]] = False
    assert _close(compiled[finite], _reference(grids, x[finite]))
    assert torch.isfinite(compiled).all() and float(compiled[3].detach().abs().max()) == 0.0
    compiled.sum().backward()
    assert all(torch.isfinite(p.grad).all() for g in grids for p in g.parameters())


def test_no_points_give_no_features_and_zero_gradients():
    grids = _grids()
    compiled = compiled_grid.read_grids(grids, torch.empty(0, 3))
    assert compiled.shape == (0, 96)
    compiled.sum().backward()
    assert all(float(p.grad.abs().max()) == 0.0 for g in grids for p in g.parameters())


def test_the_planes_stay_channel_last_through_growth_and_loading():
    """The kernel reads a plane's rows in place: a grid grown or loaded from a checkpoint saved
    before the layout (contiguous planes) keeps its channel-last layout and its values."""
    grid = VectorMatrixGrid(8, (5, 6, 7))
    old_layout = {key: value.contiguous() for key, value in grid.state_dict().items()}
    loaded = VectorMatrixGrid(8, (5, 6, 7))
    loaded.load_state_dict(old_layout)
    x = _points(50, seed=6)
    assert _close(loaded(x), grid(x))
    grid.resize((9, 9, 9))
    for parameter in [*loaded.planes, *loaded.lines, *grid.planes, *grid.lines]:
        assert parameter.is_contiguous(memory_format=torch.channels_last)
    assert compiled_grid.channel_rows(grid.planes[0]).data_ptr() == grid.planes[0].data_ptr()  # a view


def test_the_grid_fields_training_read_matches_its_separate_reads():
    """GridField.forward reads both grids in one compiled pass; density and colour are those
    of density() and colour() through PyTorch."""
    torch.manual_seed(7)
    field = GridField(GridFieldConfig(resolution=24, initial_resolution=24), SceneBounds((-1.0,) * 3, (2.0, 1.0, 1.5)))
    x = torch.rand(500, 3) * torch.tensor([3.0, 2.0, 2.5]) - 1.0
    directions = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    density, colour = field(x, directions)
    normalised = field.normalise(x)
    density_ref = field.density_from_features(field.density_grid._forward_rows(normalised).sum(-1))
    colour_ref = field.colour_from_grid(field.appearance_grid._forward_rows(normalised),
                                        field.direction_inputs(directions))
    assert _close(density, density_ref, 1e-4) and _close(colour, colour_ref)


def _march_setup(density_scale: float, wall: bool = False, clustered: bool = False):
    from nerf_backend.model_components import marcher
    from nerf_backend.model_components.occupancy import OccupancyGrid

    torch.manual_seed(0)
    field = GridField(GridFieldConfig(resolution=40, initial_resolution=40, density_shift=0.0,
                                      density_scale=density_scale), SceneBounds((-1.0, -1.0, -0.5), (1.0, 1.0, 0.5)))
    if wall:  # a faint haze (alpha ~1e-5 a step) for y < 0, then a wall: density a function of y alone
        with torch.no_grad():
            density = field.density_grid
            for parameter in (density.planes[0], density.planes[2], density.lines[0], density.lines[2]):
                parameter.zero_()
            density.planes[1].fill_(1.0)
            y = torch.linspace(-1, 1, density.lines[1].shape[2])
            summed = torch.where(y < 0, -14.0, 3.0) / density.channels  # the channels sum to -14, 3
            density.lines[1].copy_(summed.view(1, 1, -1, 1).expand_as(density.lines[1]))
    grid = OccupancyGrid(field.box_min, field.box_max, field.occupancy_cells())
    grid.occupied.copy_(torch.rand(grid.cells) > 0.6)
    rays, steps, step = 500, 120, 0.025
    origins = torch.randn(rays, 3) * 0.3 + torch.tensor([0.0, -3.0, 0.0])
    directions = torch.nn.functional.normalize(torch.randn(rays, 3) * 0.2 + torch.tensor([0.0, 1.0, 0.0]), dim=-1)
    if clustered:  # occupied cells in two balls alone, so that most blocks of 8³ cells are empty
        centres = grid.box_min + (grid.box_max - grid.box_min) * torch.rand(2, 3)
        side = (grid.box_max - grid.box_min) / torch.tensor(grid.cells)
        index = torch.stack(torch.meshgrid(*[torch.arange(n) for n in grid.cells], indexing="ij"), dim=-1)
        centre_of_cell = grid.box_min + (index + 0.5) * side
        near_a_centre = (centre_of_cell[..., None, :] - centres).norm(dim=-1).min(dim=-1).values < 0.35
        grid.occupied &= near_a_centre
        # Rays along an axis (a direction component 0) and rays that start inside the box too.
        directions[:50] = torch.tensor([0.0, 1.0, 0.0])
        origins[50:100] = origins[50:100] * 0.5 + torch.tensor([0.0, 2.0, 0.0])
        directions[50:100] = -directions[50:100]
    near, far, offset = torch.full((rays,), 1.5), torch.full((rays,), 4.5), torch.rand(rays, 1)
    # Half the rays end inside the box, where their last steps may be occupied: the march must
    # take each ray's steps up to its own far bound, not fewer, though others run on.
    ends_inside = torch.rand(rays) < 0.5
    far = torch.where(ends_inside, near + 3.0 * torch.rand(rays), far)
    edges = marcher.march_edges(near, far, step, offset, 0, steps)
    deltas = edges[:, 1:] - edges[:, :-1]
    positions = origins[:, None] + directions[:, None] * marcher.interval_midpoints(edges)[..., None]
    with torch.no_grad():
        occupied = marcher.occupied_samples(grid, positions, deltas)
        expected = marcher.lit_samples(lambda x, d: field.density(x), positions, directions, deltas, occupied)
    return field, grid, (origins, directions, near, far, offset), step, steps, occupied, expected


@pytest.mark.parametrize("clustered", [False, True], ids=["scattered", "clustered"])
@pytest.mark.parametrize("density_scale", [1.0, 300.0])
def test_the_compiled_training_march_finds_the_lit_samples_pytorchs_march_finds(density_scale, clustered):
    """marcher.occupied_samples + lit_samples against kernels/vm_grid.c's march_train: the same
    flat sample indices, in the same order (a faint field: every occupied sample is lit; a dense
    one: rays stop at their first surface). Clustered, most of the march's blocks are empty,
    some rays run along an axis and some start inside the box."""
    from nerf_backend.model_components.compiled_march import compiled_lit_samples

    field, grid, rays, step, steps, occupied, expected = _march_setup(density_scale, clustered=clustered)
    if clustered:
        assert float(grid.occupied_blocks(8).float().mean()) < 0.5 and len(expected) > 100
    with torch.no_grad():
        found, weights = compiled_lit_samples(grid, step, steps, field.compiled_density())(*rays)
    assert torch.equal(found, expected)
    # Their weights are volume rendering's over the occupied samples' densities (others count 0).
    from nerf_backend.model_components import marcher
    from nerf_backend.model_components.volume_rendering import render_weights

    origins, directions, near, far, offset = rays
    edges = marcher.march_edges(near, far, step, offset, 0, steps)
    deltas = edges[:, 1:] - edges[:, :-1]
    positions = origins[:, None] + directions[:, None] * marcher.interval_midpoints(edges)[..., None]
    with torch.no_grad():
        density = torch.zeros(deltas.numel())
        density[occupied] = field.density(positions.view(-1, 3)[occupied])
        reference, _ = render_weights(density.view(deltas.shape), deltas)
    assert float((weights - reference.view(-1)[found]).abs().max()) < 1e-5
    if density_scale > 100:  # the early stop is exercised
        assert len(expected) < (0.5 if clustered else 0.2) * len(occupied)


def test_training_colours_the_weighty_samples_and_gives_the_rest_their_rays_mean():
    """marcher.render_marched with the compiled march: the image is the one every lit sample
    coloured gives, within the weight left to the mean colour (under 1e-3 a ray here), and the
    density still gets gradients from every lit sample."""
    from nerf_backend.model_components import marcher
    from nerf_backend.model_components.compiled_march import compiled_lit_samples

    field, grid, rays, step, steps, _, _ = _march_setup(300.0, wall=True)
    lit_fn = compiled_lit_samples(grid, step, steps, field.compiled_density())
    common = dict(density_fn=lambda x, d: field.density(x), occupancy=grid, step=step, steps=steps, background=1.0,
                  offset=rays[4])
    every = marcher.render_marched(*rays[:4], field_fn=lambda x, d, c=None: GridField.forward(field, x, d), **common)
    sparse = marcher.render_marched(*rays[:4], field_fn=field, lit_fn=lit_fn, **common)
    lit, weight = lit_fn(*rays)
    assert len(marcher.colour_worthy(weight, lit // steps, 500)) < 0.8 * len(lit)  # the haze takes the mean
    assert float((sparse.rgb - every.rgb).abs().max().detach()) < 2e-3
    assert torch.allclose(sparse.opacity, every.opacity, atol=1e-5)
    sparse.rgb.sum().backward()
    line_gradient = field.density_grid.lines[1].grad[0, :, :, 0]  # [C, Ny]
    haze = torch.linspace(-1, 1, line_gradient.shape[1]) < -0.1
    assert float(line_gradient[:, haze].abs().max()) > 0  # the uncoloured haze's density still learns


def test_without_a_compiler_training_goes_through_pytorch_and_says_so_once(tiny_demo_dataset, tmp_path):
    """No C compiler: the grid preset trains (through embedding_bag and PyTorch's march and
    Adam), and one line says why, not one a step."""
    import os

    from conftest import run_python

    environment = {**os.environ, "CC": str(tmp_path / "no-such-cc"), "NERF_KERNEL_CACHE": str(tmp_path / "cache")}
    result = run_python("-m", "nerf_backend", "train", str(tiny_demo_dataset), "--out", str(tmp_path / "run"),
                        "--preset", "fast", "--iters", "20", "--no-progress", env=environment)
    assert result.stderr.count("training the grids through PyTorch") == 1, result.stderr
    assert "no-such-cc" in result.stderr
    assert (tmp_path / "run" / "checkpoint.pt").is_file()


@pytest.mark.parametrize("resolution", [24, 2], ids=["uneven sides", "one cell"])
def test_the_training_occupancy_estimate_in_place_equals_the_vertex_densitys(resolution):
    """GridField.occupancy_estimate in training (the dense sum activated and maxed in its own
    memory) against VertexOccupancy's (vertex_density, then cell_corner_max): the same cell
    maxima to the bit and the same mean to float rounding, with densities from empty to the
    softplus's linear part; out of training the dense sum rendering caches is left unchanged."""
    from nerf_backend.fields.base import VertexOccupancy

    field = GridField(GridFieldConfig(resolution=resolution, initial_resolution=resolution, cubic_cells=resolution > 2),
                      SceneBounds((-1.0,) * 3, (2.0, 1.0, 1.5)))
    generator = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for parameter in field.density_grid.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator) * 3.0)
    for training in (True, False):
        field.train(training)
        cached = None if training else field._dense_density().clone()
        cell_max, mean = field.occupancy_estimate()
        expected_max, expected_mean = VertexOccupancy.occupancy_estimate(field)
        assert cell_max.shape == expected_max.shape == tuple(n - 1 for n in field.vertices)
        assert torch.equal(cell_max, expected_max)
        assert mean == pytest.approx(expected_mean, rel=1e-6)
        if cached is not None:
            assert torch.equal(field._dense_density(), cached)
    if resolution > 2:
        assert len(set(field.vertices)) == 3  # a side each
        assert float(cell_max.max()) > 10 * field.config.density_scale and float(cell_max.min()) < 1e-3


@pytest.mark.parametrize("resolution", [24, 2], ids=["uneven sides", "one cell"])
def test_renderings_cell_maxima_from_the_sums_maxima_equal_the_vertex_densitys(resolution):
    """GridField.cell_max_density (the dense sum's cell maxima, then only they activated)
    against VertexOccupancy's (every vertex activated, then the maxima): the same cell maxima to
    float32 rounding (softplus is increasing, to within its own last bit), densities from empty
    to softplus's linear part; the dense sum rendering caches left unchanged."""
    from nerf_backend.fields.base import VertexOccupancy

    field = GridField(GridFieldConfig(resolution=resolution, initial_resolution=resolution, cubic_cells=resolution > 2),
                      SceneBounds((-1.0,) * 3, (2.0, 1.0, 1.5))).eval()
    generator = torch.Generator().manual_seed(4)
    with torch.no_grad():
        for parameter in field.density_grid.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator) * 3.0)
    cached = field._dense_density().clone()
    cell_max, expected = field.cell_max_density(), VertexOccupancy.cell_max_density(field)
    assert cell_max.shape == expected.shape == tuple(n - 1 for n in field.vertices)
    assert torch.allclose(cell_max, expected, rtol=2e-7, atol=0)
    assert torch.equal(field._dense_density(), cached)
    if resolution > 2:
        assert float(cell_max.max()) > 10 * field.config.density_scale and float(cell_max.min()) < 1e-3
