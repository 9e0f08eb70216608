"""Inference's compiled colour pass (kernels/colour_network.h through
field_components/compiled_colour.py) against PyTorch's colour, which is the reference: the grid
read through PyTorch's own gather (``_forward_rows``), then the appearance basis, the
direction's encoding and the three layers, on uneven sample counts (the pass goes in tiles),
points inside, on the border of and outside the box, any thread count.

Where the pass multiplies in float32, the same colours within 2e-6 (float32 rounding of sums of
72 and 64 terms). Where it multiplies the two wide layers in bfloat16 (a CPU with AVX512-BF16:
``colour_precision``), the reference rounds the same inputs and weights to bfloat16 and sums in
float32: the same to float32 rounding but where a hidden value lands on the other side of a
bfloat16 rounding from summing in another order (2^-8 of it, up to 3e-3 of a colour with these
random weights: 2e-6 on average), and within 2e-2 of float32's colours, as PyTorch's own
bfloat16 products are (tests/test_fast_model.py)."""

from __future__ import annotations

import ctypes
import dataclasses

import pytest
import torch
from conftest import X86_LEVELS, cpu_runs_x86_level

from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.field_components import compiled_colour, compiled_grid
from nerf_backend.fields.grid_field import GridField, GridFieldConfig

BOX = SceneBounds((-0.7, -1.2, -0.4), (0.9, 1.1, 1.3))  # uneven sides: the normalisation per axis


@pytest.fixture(scope="module", autouse=True)
def library():
    found = compiled_grid.compiled_grid_library()
    if found is None:
        pytest.skip("no C compiler here: the compiled colour is not built (PyTorch colours)")
    return found


def _field(**settings) -> GridField:
    torch.manual_seed(3)
    config = dataclasses.replace(GridFieldConfig(initial_resolution=13, resolution=13), **settings)
    field = GridField(config, BOX).eval()
    with torch.no_grad():
        for parameter in field.parameters():
            parameter.normal_(0.0, 0.3)  # random weights: colours that differ, not the start's grey
    return field


def _reference(field: GridField, x: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    features = field.appearance_grid._forward_rows(field.normalise(x))
    return field.colour_from_grid(features, field.direction_inputs(directions))


def _bfloat16(t: torch.Tensor) -> torch.Tensor:
    return t.to(torch.bfloat16).float()


def _reference_bfloat16(field: GridField, x: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """``_reference`` with the two wide layers' inputs and weights rounded to bfloat16 (the
    appearance basis folded into the first layer first, as the pass does)."""
    first, second, third = field.colour_mlp[0], field.colour_mlp[2], field.colour_mlp[4]
    appearance = field.config.appearance_dims
    features = field.appearance_grid._forward_rows(field.normalise(x))
    folded = (first.weight[:, :appearance] @ field.appearance_basis.weight).t()
    per_sample = torch.nn.functional.linear(field.direction_encoding(directions), first.weight[:, appearance:],
                                            first.bias)
    hidden = (per_sample + _bfloat16(features) @ _bfloat16(folded)).relu()
    hidden = (second.bias + _bfloat16(hidden) @ _bfloat16(second.weight.t())).relu()
    return torch.sigmoid(third(hidden))


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("count", [1, 5, 6, 7, 4099])
def test_colours_match_pytorchs(threads, count, monkeypatch):
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    field = _field()
    generator = torch.Generator().manual_seed(count)
    directions = torch.nn.functional.normalize(torch.randn(37, 3, generator=generator), dim=-1)
    ray = torch.randint(0, 37, (count,), generator=generator)
    low, high = torch.tensor(BOX.box_min), torch.tensor(BOX.box_max)
    # 5 % past each side of the box: the grid's border fades as in PyTorch's read
    x = low + (torch.rand(count, 3, generator=generator) * 1.1 - 0.05) * (high - low)
    with torch.no_grad():
        colour = compiled_colour.compiled_ray_colour(field, directions, torch.bfloat16)
        assert colour is not None
        actual = colour(x, ray)
        expected = _reference(field, x, directions.index_select(0, ray))
        rounded = _reference_bfloat16(field, x, directions.index_select(0, ray))
    assert actual.shape == (count, 3) and actual.dtype == torch.float32
    if compiled_colour.colour_precision() == 32:
        assert float((actual - expected).abs().max()) <= 2e-6
    else:
        assert float((actual - rounded).abs().max()) <= 3e-3
        assert float((actual - rounded).abs().mean()) <= 2e-6
        assert float((actual - expected).abs().max()) < 2e-2
    if count > 1000:
        assert float(expected.std()) > 0.05


def test_the_pass_is_what_the_grid_field_colours_with_on_the_cpu_at_the_precision_asked():
    field = _field()
    directions = torch.nn.functional.normalize(torch.randn(4, 3), dim=-1)
    assert isinstance(field.ray_colour(directions, torch.bfloat16), compiled_colour.CompiledRayColour)
    # float32 asked: a pass that multiplies in bfloat16 leaves it to PyTorch
    in_float32 = field.ray_colour(directions, torch.float32)
    assert isinstance(in_float32, compiled_colour.CompiledRayColour) == (compiled_colour.colour_precision() == 32)


@pytest.mark.parametrize("settings, why", [
    ({"hidden_width": 32}, "a network of another width"),
    ({"appearance_channels": 12}, "channels that are not whole vectors of 8"),
])
def test_other_networks_colour_through_pytorch(settings, why):
    field = _field(**settings)
    directions = torch.nn.functional.normalize(torch.randn(9, 3), dim=-1)
    assert compiled_colour.compiled_ray_colour(field, directions, torch.bfloat16) is None, why
    ray = torch.arange(9).repeat(3)
    x = torch.zeros(27, 3)
    with torch.no_grad():  # PyTorch's colour still runs
        assert torch.allclose(field.ray_colour(directions)(x, ray), _reference(field, x, directions[ray]), atol=1e-6)


def test_a_field_in_another_precision_colours_through_pytorch():
    field = _field().to(torch.float64)
    directions = torch.nn.functional.normalize(torch.randn(3, 3, dtype=torch.float64), dim=-1)
    assert compiled_colour.compiled_ray_colour(field, directions, torch.bfloat16) is None


def test_nerf_kernel_target_builds_every_kernel_for_that_level(monkeypatch):
    """NERF_KERNEL_TARGET=x86-64-v3: the AVX2 machines' code, run here (docs/testing.md)."""
    from nerf_backend.kernels.build import TARGET_VARIABLE, load_kernel
    if not cpu_runs_x86_level("x86-64-v3"):
        pytest.skip("this CPU cannot run code for x86-64-v3")
    monkeypatch.setenv(TARGET_VARIABLE, "x86-64-v3")
    chosen = load_kernel("vm_grid")
    assert chosen[0] is not None and chosen == load_kernel("vm_grid", "x86-64-v3")
    monkeypatch.delenv(TARGET_VARIABLE)
    assert load_kernel("vm_grid")[0] is not chosen[0]  # the running CPU's own build


def _library_for(level: str) -> ctypes.CDLL:
    """The grid kernel built for ``-march=level`` (skipped where this CPU cannot run it), with
    the return types the passes' callers give it."""
    from nerf_backend.kernels.build import load_kernel
    if not cpu_runs_x86_level(level):
        pytest.skip(f"this CPU cannot run code for {level}")
    library, why_not = load_kernel("vm_grid", level)
    assert library is not None, why_not
    for name in ("colour_samples", "shade_rays", "shade_rays_training_forward", "shade_rays_training_backward"):
        getattr(library, name).restype = ctypes.c_int
    library.shade_training_gradient_floats.restype = ctypes.c_int64
    library.shade_training_room_floats.restype = ctypes.c_int64
    library.shade_training_prepare.restype = None
    return library


@pytest.mark.parametrize("level", sorted(X86_LEVELS))
def test_the_pass_built_for_each_vector_width_the_cpu_runs_colours_as_pytorch(level):
    """Each vector width's code (conftest's X86_LEVELS) colours as PyTorch does."""
    library = _library_for(level)
    field = _field()
    generator = torch.Generator().manual_seed(11)
    directions = torch.nn.functional.normalize(torch.randn(37, 3, generator=generator), dim=-1)
    ray = torch.randint(0, 37, (1001,), generator=generator)
    low, high = torch.tensor(BOX.box_min), torch.tensor(BOX.box_max)
    x = low + torch.rand(1001, 3, generator=generator) * (high - low)
    with torch.no_grad():
        layers = compiled_colour._linear_layers(field.colour_mlp)
        actual = compiled_colour.CompiledRayColour(field, directions, layers, library)(x, ray)
        expected = _reference(field, x, directions.index_select(0, ray))
    assert float((actual - expected).abs().max()) <= 2e-6
    assert float(expected.std()) > 0.05


# Deferred colour's compiled shading (colour_network.h's shade_rays, CompiledShade) against
# PyTorch's shade_fn through volume_rendering.shade_rays: the same colours within 5e-6 (float32
# rounding of the mean's division, the encoding's sin and cos, and sums of 87 and 64 terms in
# another order, the appearance basis folded into the first layer; with these random weights
# and features the sums reach about 30, whose float32 step is 2e-6), rays not shaded black,
# any ray count (tiles of 6) and thread count.

def _pytorch_shade(field: GridField):
    return lambda mean, directions: field.colour_from_grid(mean, field.direction_inputs(directions))


def _composited(field: GridField, rays: int, seed: int):
    """What a view's compositing leaves each ray: features Σ w·f, coloured weight Σ w (a third of
    the rays 0: nothing coloured; some just above MIN_SHADED_WEIGHT), whole weight, direction."""
    generator = torch.Generator().manual_seed(seed)
    coloured = torch.rand(rays, generator=generator) * 0.9 + 0.1
    coloured[torch.rand(rays, generator=generator) < 1 / 3] = 0.0
    coloured[::17] = 3e-12
    features = torch.randn(rays, field.appearance_grid.out_dims, generator=generator) * coloured[:, None]
    weight = coloured * (1.0 + 0.05 * torch.rand(rays, generator=generator))
    directions = torch.nn.functional.normalize(torch.randn(rays, 3, generator=generator), dim=-1)
    return features, coloured, weight, directions


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("rays", [1, 5, 6, 7, 4099])
@pytest.mark.parametrize("bands", [0, 2, 4])
def test_the_compiled_shading_equals_pytorchs(bands, rays, threads, monkeypatch):
    from nerf_backend.model_components.volume_rendering import shade_rays
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    field = _field(deferred_colour=True, direction_frequencies=bands)
    composited = _composited(field, rays, seed=rays + bands)
    with torch.no_grad():
        compiled = compiled_colour.compiled_shade(field)
        assert compiled is not None
        actual = shade_rays(*composited, compiled)
        expected = shade_rays(*composited, _pytorch_shade(field))
        mean, directions = composited[0][:3] / composited[1][:3, None].clamp(min=1e-12), composited[3][:3]
        called = compiled(mean, directions)  # the plain ShadeFn call: weight 1, every ray shaded
        called_expected = _pytorch_shade(field)(mean, directions)
    assert actual.shape == (rays, 3) and actual.dtype == torch.float32
    assert float((actual - expected).abs().max()) <= 5e-6
    unshaded = composited[1] <= 1e-12
    assert bool((actual[unshaded] == 0).all())
    assert float((called - called_expected).abs().max()) <= 5e-6
    if rays > 1000:
        assert float(expected[~unshaded].std()) > 0.05


def test_the_compiled_shading_is_kept_until_the_network_or_the_basis_changes():
    """``compiled_shade`` gives the same pass while the weights stay (a view's chunks each ask),
    and a new one that shades as PyTorch does once an optimiser-like in-place step changes the
    first layer or the basis."""
    from nerf_backend.model_components.volume_rendering import shade_rays
    field = _field(deferred_colour=True, direction_frequencies=2)
    composited = _composited(field, 300, seed=4)
    with torch.no_grad():
        kept = compiled_colour.compiled_shade(field)
        assert kept is not None and compiled_colour.compiled_shade(field) is kept
        for weight in (field.colour_mlp[0].weight, field.appearance_basis.weight):
            weight.add_(0.05 * torch.randn_like(weight))
            fresh = compiled_colour.compiled_shade(field)
            assert fresh is not kept
            error = (shade_rays(*composited, fresh) - shade_rays(*composited, _pytorch_shade(field))).abs().max()
            assert float(error) <= 5e-6
            kept = fresh


def test_a_network_the_passes_do_not_take_shades_through_pytorch_in_training_and_at_inference():
    field = _field(deferred_colour=True, hidden_width=32)
    with torch.no_grad():
        assert not isinstance(field.shade_fn(), compiled_colour.CompiledShade)
    shade = field.shade_fn()  # gradients wanted: PyTorch's, which autograd follows
    assert not isinstance(shade, compiled_colour.CompiledShadeTraining)
    mean = torch.randn(5, field.appearance_grid.out_dims, requires_grad=True)
    shade(mean, torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)).sum().backward()
    assert mean.grad is not None and field.colour_mlp[0].weight.grad is not None


@pytest.mark.parametrize("settings, why", [
    ({"hidden_width": 32}, "a network of another width"),
    ({"view_dependent": False}, "a network without the direction"),
    ({"direction_frequencies": 9}, "more bands than the pass encodes"),
])
def test_other_networks_shade_through_pytorch(settings, why):
    field = _field(deferred_colour=True, **settings)
    assert compiled_colour.compiled_shade(field) is None, why
    with torch.no_grad():
        assert not isinstance(field.shade_fn(), compiled_colour.CompiledShade)
    assert compiled_colour.compiled_shade(_field(deferred_colour=True).to(torch.float64)) is None


# Training's compiled shading (CompiledShadeTraining: the basis and the network forward and
# backward in one call each) against PyTorch's autograd over the same network: the colour
# within 5e-6 and every gradient (the mean features' and each parameter's) within 1e-5 of the
# largest of its kind plus 2e-5 of each value (float32 sums of up to 1 000 rays in another order).

def _training_case(field: GridField, rays: int, seed: int):
    generator = torch.Generator().manual_seed(seed)
    mean = torch.randn(rays, field.appearance_grid.out_dims, generator=generator)
    directions = torch.nn.functional.normalize(torch.randn(rays, 3, generator=generator), dim=-1)
    upstream = torch.randn(rays, 3, generator=generator)
    return mean, directions, upstream


def _gradients(field: GridField, shade, mean, directions, upstream):
    field.zero_grad(set_to_none=True)
    mean = mean.clone().requires_grad_(True)
    colour = shade(mean, directions)
    (colour * upstream).sum().backward()
    named = {name: p.grad.clone() for name, p in field.named_parameters() if p.grad is not None}
    return colour.detach(), mean.grad, named


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("rays", [1, 5, 6, 7, 1000])
@pytest.mark.parametrize("bands", [0, 2])
def test_the_compiled_training_shading_equals_autograds(bands, rays, threads, monkeypatch):
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    field = _field(deferred_colour=True, direction_frequencies=bands).train()
    compiled = compiled_colour.compiled_shade_training(field)
    assert compiled is not None
    case = _training_case(field, rays, seed=rays + 10 * bands)
    colour, grad_mean, grads = _gradients(field, compiled, *case)
    expected_colour, expected_mean, expected = _gradients(field, _pytorch_shade(field), *case)
    assert float((colour - expected_colour).abs().max()) <= 5e-6
    trained = {"appearance_basis.weight", "colour_mlp.0.weight", "colour_mlp.0.bias", "colour_mlp.2.weight",
               "colour_mlp.2.bias", "colour_mlp.4.weight", "colour_mlp.4.bias"}
    assert set(grads) == set(expected) == trained
    for name, actual, reference in [("mean", grad_mean, expected_mean)] + [(n, grads[n], expected[n]) for n in trained]:
        assert actual.shape == reference.shape, name
        bound = 1e-5 * float(reference.abs().max()) + 2e-5 * reference.abs()
        assert bool(((actual - reference).abs() <= bound).all()), (name, float((actual - reference).abs().max()))
    if rays == 1000:
        assert float(expected["colour_mlp.0.weight"].abs().max()) > 1e-2  # gradients that say something


@pytest.mark.parametrize("threads", [1, 2])
def test_training_shades_whole_rays_in_one_node_with_autograds_colour_and_gradients(threads, monkeypatch):
    """``shade_rays`` in training through the compiled pass's own hook: one autograd node (the
    gathers, the division, the network, the weighting and the scatter), its image and the
    gradients of the features, both weights and every parameter those of PyTorch's operations;
    rays without coloured weight stay black and get no gradient."""
    from nerf_backend.model_components.volume_rendering import shade_rays
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    field = _field(deferred_colour=True).train()
    compiled = compiled_colour.compiled_shade_training(field)
    composited = _composited(field, 1500, seed=8)
    upstream = torch.randn(1500, 3, generator=torch.Generator().manual_seed(9))

    def run(shade):
        field.zero_grad(set_to_none=True)
        inputs = [t.clone().requires_grad_(True) for t in composited[:3]]
        rgb = shade_rays(*inputs, composited[3], shade)
        (rgb * upstream).sum().backward()
        named = {name: p.grad.clone() for name, p in field.named_parameters() if p.grad is not None}
        return rgb, [t.grad for t in inputs], named

    rgb, grads, named = run(compiled)
    expected_rgb, expected_grads, expected_named = run(_pytorch_shade(field))
    assert type(rgb.grad_fn).__name__ == "_ShadeRaysTrainingFunctionBackward"
    unshaded = composited[1] <= 1e-12
    assert 300 < int(unshaded.sum()) < 700 and not rgb[unshaded].any() and not grads[0][unshaded].any()
    assert float((rgb - expected_rgb).detach().abs().max()) <= 5e-6
    assert set(named) == set(expected_named) and len(named) == 7
    pairs = zip(["features", "coloured weight", "weight"] + sorted(named), grads + [named[n] for n in sorted(named)],
                expected_grads + [expected_named[n] for n in sorted(named)])
    for name, actual, reference in pairs:
        assert actual.shape == reference.shape, name
        bound = 1e-5 * float(reference.abs().max()) + 2e-5 * reference.abs()
        assert bool(((actual - reference).abs() <= bound).all()), (name, float((actual - reference).abs().max()))
        assert float(reference.abs().max()) > 1e-3, name  # gradients that say something


def test_training_shading_of_no_rays_gives_empty_colours_and_zero_gradients():
    """No ray to shade: an empty image, and the parameters' gradients zero (not unset), as
    autograd's through PyTorch's operations on no rows."""
    field = _field(deferred_colour=True).train()
    compiled = compiled_colour.compiled_shade_training(field)
    mean, directions, upstream = _training_case(field, 0, seed=1)
    colour, grad_mean, grads = _gradients(field, compiled, mean, directions, upstream)
    _, _, expected = _gradients(field, _pytorch_shade(field), mean, directions, upstream)
    assert colour.shape == (0, 3) and grad_mean.shape == mean.shape
    assert set(grads) == set(expected) and all(not g.any() for g in grads.values())


def test_the_grid_field_trains_its_shading_through_the_compiled_pass_outside_autocast():
    field = _field(deferred_colour=True).train()
    assert isinstance(field.shade_fn(), compiled_colour.CompiledShadeTraining)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not isinstance(field.shade_fn(), compiled_colour.CompiledShadeTraining)
    with torch.no_grad():
        assert isinstance(field.shade_fn(), compiled_colour.CompiledShade)


@pytest.mark.parametrize("level", sorted(X86_LEVELS))
def test_the_shadings_built_for_each_vector_width_the_cpu_runs_shade_and_train_as_pytorch(level):
    """Each vector width's code (its own tile of rays by outputs) shades as PyTorch does, and
    trains with autograd's gradients."""
    from nerf_backend.model_components.volume_rendering import shade_rays
    library = _library_for(level)
    field = _field(deferred_colour=True)
    case = _training_case(field, 999, seed=6)
    _, grad_mean, grads = _gradients(field, compiled_colour.CompiledShadeTraining(field, library), *case)
    _, expected_mean, expected_grads = _gradients(field, _pytorch_shade(field), *case)
    for actual, reference in [(grad_mean, expected_mean)] + [(grads[n], expected_grads[n]) for n in expected_grads]:
        assert bool(((actual - reference).abs() <= 1e-5 * float(reference.abs().max()) + 2e-5 * reference.abs()).all())
    composited = _composited(field, 1001, seed=5)
    with torch.no_grad():
        compiled = compiled_colour.CompiledShade(field, compiled_colour._linear_layers(field.colour_mlp), library)
        actual = shade_rays(*composited, compiled)
        expected = shade_rays(*composited, _pytorch_shade(field))
    assert float((actual - expected).abs().max()) <= 5e-6
