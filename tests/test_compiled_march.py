"""The compiled CPU march (nerf_backend/kernels/march_render.c) against PyTorch's: the same
rays through the same models must give the same image, depth and opacity to the bounds the
two inference shortcuts allow (the early stop, the faint weight left uncoloured), for the
grid field's softplus and the surface field's Laplace density; a ray that needs more packed
samples than the buffer holds is marched again into a larger one; no compiler is an answer
with its reason, and the model then renders through PyTorch."""

from __future__ import annotations

import ctypes
import dataclasses
import math

import pytest
import torch

from conftest import X86_LEVELS, cpu_runs_x86_level, rays_through_box
from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.cameras import Intrinsics, camera_rays, pixel_centres, ray_box_intersection
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.kernels import build
from nerf_backend.model_components import compiled_march
from nerf_backend.model_components.marcher import (DRAFT_STOP, EXACT_STOP, OPAQUE_TRANSMITTANCE, SKIPPED_WEIGHT,
                                                   render_marched_stopping_early)
from nerf_backend.models import marched
from nerf_backend.models.registry import build_model

BOX = SceneBounds((-1.0, -1.2, -0.8), (1.0, 1.2, 0.8))  # not a cube: the axes must not be swapped


@pytest.fixture(scope="module")
def library():
    found, reason = compiled_march.compiled_march_library()
    if found is None:
        pytest.fail(f"the compiled march must build here (make setup's machines have gcc): {reason}")
    return found


def _model(preset: str, seed: int, spread: float, **surface):
    """A model of ``preset`` with random smooth colour and, but for the surface field (which
    starts as a sphere), random smooth blobs of density (``spread``: their contrast; the surface
    field's distance is multiplied by it instead), occupancy updated, in inference mode."""
    torch.manual_seed(seed)
    config = PRESETS[preset]
    if surface:  # the surface field's settings (its opacity)
        config = config.with_settings(surface=dataclasses.replace(config.surface, **surface))
    model = build_model(config, BOX)
    vertices = model.field.vertices
    model.resize((5, 6, 4))
    kept = {id(p) for p in getattr(model.field, "sdf_grid", torch.nn.Module()).parameters()}
    with torch.no_grad():
        for parameter in model.field.encoding_parameters():
            if id(parameter) not in kept:
                parameter.normal_(0.0, spread)
    model.resize(vertices)
    if kept:  # the sphere, coarsened by the resizing above, is shallow: spread deepens it
        with torch.no_grad():
            model.field.sdf_grid.values.mul_(spread)
    model.update_occupancy()
    return model.eval()


def _both(model, rays, library):
    """The image through the compiled march (as the model renders on the CPU) and through
    PyTorch's march, from the same occupancy and density volume; the reference colours each
    sample with ``colour`` along its own direction, the model once a ray (``ray_colour``)."""
    directions = rays[1]
    with torch.no_grad():
        compiled = model(*rays)[0]
        march = dict(occupancy=model.render_occupancy(), step=model.step, steps=model.samples_per_ray, background=1.0,
                     stop=model.ray_stop)
        reference = render_marched_stopping_early(
            *rays, density_fn=model._frozen_density,
            ray_colour=lambda x, ray: model.field.colour(x, directions.index_select(0, ray)), **march)
        density, used = model._compiled_density(rays[0].device)
    assert used is library and density.volume.shape[::-1] == model.field.vertices  # the model took the compiled path
    return compiled, reference


@pytest.mark.parametrize("threads", [1, 2, 3])  # the march splits its rays over the threads torch has
@pytest.mark.parametrize("preset, spread, surface", [("fast", 1.4, {}), ("auto", 1.4, {}), ("surface", 1.0, {}),
                                                     ("surface", 20.0, {"opacity": "neus"})])
def test_the_compiled_march_renders_pytorchs_image(preset, spread, surface, threads, library, monkeypatch):
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    model = _model(preset, seed=3, spread=spread, **surface)
    assert 0.01 < model.occupancy.occupied_fraction < 0.98  # both kinds of space
    compiled, reference = _both(model, rays_through_box(BOX, 3000, seed=4), library)
    opaque = reference.opacity > 1 - OPAQUE_TRANSMITTANCE
    assert 0 < opaque.sum() < len(opaque)  # rays that stop and rays that pass through
    # Each path stops a ray somewhere below 1e-4 transmittance and leaves up to 1e-3 of its
    # weight to its mean colour, each by its own rule: the images differ by at most the sum.
    bound = 2 * OPAQUE_TRANSMITTANCE + 2 * SKIPPED_WEIGHT + 1e-5
    assert (compiled.rgb - reference.rgb).abs().max() < bound
    assert (compiled.opacity - reference.opacity).abs().max() < 2 * OPAQUE_TRANSMITTANCE + 1e-5
    far = float(rays_through_box(BOX, 1, seed=4)[3].max()) + 8.0
    assert (compiled.depth - reference.depth).abs().max() < 2 * OPAQUE_TRANSMITTANCE * far + 1e-4
    assert (compiled.rgb - reference.rgb).abs().mean() < 1e-4


def test_a_draft_stops_its_rays_sooner_in_both_marches(library):
    """Inside ``march_step_scaled(2)`` (the live view's drafts) a ray stops once 99 % of its
    light is taken (``DRAFT_STOP``), in the compiled march and PyTorch's alike: the two images
    agree within the draft stop's bounds, opaque rays keep up to 1e-2 of their light (some more
    than the exact stop's 1e-4), and the exact stop is back after the block."""
    model = _model("fast", seed=3, spread=1.4)
    rays = rays_through_box(BOX, 3000, seed=4)
    with model.march_step_scaled(2.0):
        assert model.ray_stop == DRAFT_STOP
        compiled, reference = _both(model, rays, library)
    assert model.ray_stop == EXACT_STOP
    bound = 2 * DRAFT_STOP.opaque_transmittance + 2 * DRAFT_STOP.skipped_weight + 1e-5
    assert (compiled.rgb - reference.rgb).abs().max() < bound
    assert (compiled.opacity - reference.opacity).abs().max() < 2 * DRAFT_STOP.opaque_transmittance + 1e-5
    stopped = compiled.opacity > 1 - DRAFT_STOP.opaque_transmittance
    assert stopped.sum() > 100
    assert (compiled.opacity[stopped] < 1 - EXACT_STOP.opaque_transmittance).sum() > 10


def test_a_translucent_field_overflows_the_sample_buffer_and_is_marched_again(library, monkeypatch):
    """A haze of even density over the whole box (σ = 0.5: no ray stops): every ray colours
    about as many samples as it has steps, and with room for 4096 samples a call the rays left
    undone are marched again in later calls."""
    monkeypatch.setattr(compiled_march, "SAMPLES_PER_CALL", 4096)
    model = _model("fast", seed=5, spread=1.0)
    field = model.field.config
    # σ = scale · softplus(Σ plane·line + shift): every one of the 3·C products the same.
    summed = math.log(math.expm1(0.5 / field.density_scale)) - field.density_shift
    with torch.no_grad():
        for parameter in model.field.density_grid.parameters():
            parameter.fill_(math.sqrt(summed / (3 * field.density_channels)))
    model.update_occupancy()
    assert model.occupancy.occupied_fraction == 1.0
    calls = []
    original = library.march_render

    class Counting:
        restype = original.restype

        def __call__(self, *args):
            calls.append(args[9].value)  # the rays the call marches
            return original(*args)

    monkeypatch.setattr(library, "march_render", Counting())
    compiled, reference = _both(model, rays_through_box(BOX, 1024, seed=6), library)
    assert len(calls) > 2 and calls[0] == 1024 and all(a > b > 0 for a, b in zip(calls, calls[1:]))  # fewer each time
    assert float(reference.opacity.min()) < 0.9  # translucent: no early stop
    assert (compiled.rgb - reference.rgb).abs().max() < 2 * SKIPPED_WEIGHT + 1e-5
    assert (compiled.opacity - reference.opacity).abs().max() < 1e-4


@pytest.mark.parametrize("level", sorted(X86_LEVELS))
def test_the_march_built_for_each_vector_width_renders_the_same_image(level, library, monkeypatch):
    """The march looks its steps up 8 at a time in vectors (4 floats wide at x86-64, 8 at
    x86-64-v3) with the float operations of one step at a time: each level's build reads the
    same steps as this CPU's own, so the images are equal bit for bit."""
    if not cpu_runs_x86_level(level):
        pytest.skip(f"this CPU cannot run code for {level}")
    leveled, why_not = build.load_kernel("march_render", level)
    assert leveled is not None, why_not
    leveled.march_render.restype = ctypes.c_int64
    model = _model("auto", seed=3, spread=1.4)
    rays = rays_through_box(BOX, 3000, seed=4)
    with torch.no_grad():
        native = model(*rays)[0]
        monkeypatch.setattr(marched, "compiled_march_library", lambda: (leveled, None))
        assert model._compiled_density(rays[0].device)[1] is leveled
        built = model(*rays)[0]
    assert 0 < int((native.opacity > 0.5).sum()) < 3000
    for name in ("rgb", "depth", "opacity"):
        assert torch.equal(getattr(built, name), getattr(native, name)), name


def test_the_compiled_box_stretch_is_pytorchs_bit_for_bit(library):
    """``ray_box_stretch`` on the CPU (march_render.c's ``rays_through_box``) against
    ``ray_box_intersection`` and the narrowing through PyTorch: rays from outside and inside the
    box, rays along an axis (a zero component), rays that miss, and NaN and infinite parts, all
    equal to the last bit (NaN where PyTorch has NaN)."""
    generator = torch.Generator().manual_seed(12)
    origins = torch.randn(5000, 3, generator=generator) * 3
    directions = torch.nn.functional.normalize(torch.randn(5000, 3, generator=generator), dim=-1)
    aimed = torch.rand(2500, 3, generator=generator) * 1.6 - 0.8  # points in the box
    directions[520:3020] = torch.nn.functional.normalize(aimed - origins[520:3020], dim=-1)
    directions[:300, 0] = 0.0  # along the y-z plane
    directions[300:400, :2] = 0.0
    directions[300:400, 2] = -1.0
    directions[400:410, 1] = float("nan")
    origins[410:420, 2] = float("inf")
    origins[420:520] = torch.rand(100, 3, generator=generator) * 1.6 - 0.8  # inside the box
    box_min, box_max = torch.tensor([-1.0, -1.2, -0.8]), torch.tensor([1.0, 1.2, 0.8])
    assert compiled_march.compiled_march_library()[0] is library
    near, far = compiled_march.ray_box_stretch(origins, directions, box_min, box_max)
    entry, exit_, hit = ray_box_intersection(origins, directions, box_min, box_max)
    assert 1000 < int(hit.sum()) < 4000 and near[420:520].eq(0).all()
    assert torch.equal(near.nan_to_num(7.0), entry.nan_to_num(7.0)) and torch.equal(far.nan_to_num(7.0), exit_.nan_to_num(7.0))
    assert near.isnan().sum() >= 10 and torch.equal(near.isnan(), entry.isnan())
    within = (torch.rand(5000, generator=generator) * 2, 2 + torch.rand(5000, generator=generator) * 3)
    narrowed = compiled_march.ray_box_stretch(origins, directions, box_min, box_max, within=within)
    expected_near = torch.maximum(within[0], entry)
    expected_far = torch.maximum(torch.minimum(within[1], exit_), expected_near)
    assert torch.equal(narrowed[0].nan_to_num(7.0), expected_near.nan_to_num(7.0))
    assert torch.equal(narrowed[1].nan_to_num(7.0), expected_far.nan_to_num(7.0))
    assert within[0].isnan().sum() == 0  # the stretch given is left as it was


def test_the_compiled_pixel_rays_are_pytorchs_camera_rays(library):
    """``pixel_rays`` on the CPU (march_render.c) against ``camera_rays`` of ``pixel_centres``:
    a chunk of a wide image from its middle (rows wrapping), a rotated and moved camera whose
    focal lengths differ and whose principal point is off centre: the same origins, and
    directions within 2 float32 steps (the rotation's sums are added in another order)."""
    intrinsics = Intrinsics(37, 23, 41.0, 45.5, 17.25, 12.0)
    rotation = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(13)))[0]
    pose = torch.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, torch.tensor([0.5, -2.0, 3.0])
    assert compiled_march.compiled_march_library()[0] is library
    origins, directions = compiled_march.pixel_rays(intrinsics, pose, 100, 700)
    expected = camera_rays(intrinsics, pose, pixel_centres(37, torch.arange(100, 700)))
    assert torch.equal(origins, expected[0])
    assert (directions - expected[1]).abs().max() <= 2 * torch.finfo(torch.float32).eps
    assert torch.allclose(directions.norm(dim=-1), torch.ones(600), atol=2e-7)


def test_without_a_compiler_the_reason_is_given_and_nothing_is_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setenv(build.CACHE_VARIABLE, str(tmp_path / "cache"))
    library, reason = build._load_kernel.__wrapped__("march_render", build.NATIVE_TARGET)
    assert library is None and "no-such-cc" in reason and "march_render.c" in reason
    assert not list((tmp_path / "cache").glob("*.so"))


def test_a_missing_source_is_a_reason_not_a_crash(tmp_path, monkeypatch):
    """A partial install (an extension zip that left a kernel out) still trains and renders
    through PyTorch: the missing file is named, nothing is raised."""
    monkeypatch.setattr(build, "SOURCES", tmp_path)
    library, reason = build._load_kernel.__wrapped__("march_render", build.NATIVE_TARGET)
    assert library is None and str(tmp_path / "march_render.c") in reason and "cannot be read" in reason


def test_a_kernel_is_built_once_into_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(build.CACHE_VARIABLE, str(tmp_path))
    first, reason = build._load_kernel.__wrapped__("march_render", build.NATIVE_TARGET)
    assert first is not None, reason
    built = list(tmp_path.glob("march_render-*.so"))
    assert len(built) == 1 and not [p for p in tmp_path.iterdir() if p.is_dir()]  # no scratch left
    stamp = built[0].stat().st_mtime_ns
    second, _ = build._load_kernel.__wrapped__("march_render", build.NATIVE_TARGET)
    assert second is not None and built[0].stat().st_mtime_ns == stamp


def test_rays_with_nan_or_infinite_parts_leave_the_others_as_they_were(library):
    """A float cast to an index must be in range in C: NaN or infinite origins, directions and
    bounds are clamped before any cast, and the finite rays render as they do alone."""
    model = _model("fast", seed=3, spread=1.4)
    origins, directions, near, far = rays_through_box(BOX, 64, seed=1)
    with torch.no_grad():
        alone = model(origins[5:], directions[5:], near[5:], far[5:])[0]
        origins[0], directions[1], near[2], far[3], origins[4] = float("nan"), float("inf"), float("nan"), float("inf"), 1e30
        mixed = model(origins, directions, near, far)[0]
    # The march's samples are the same; the colour network's matrix products may round
    # differently for another batch of samples (measured: one ray 6e-8 apart).
    assert torch.allclose(mixed.rgb[5:], alone.rgb, rtol=0, atol=1e-6)
    assert torch.allclose(mixed.depth[5:], alone.depth, rtol=0, atol=1e-5)
    assert torch.equal(mixed.opacity[5:], alone.opacity)  # density: no matrix products
    assert torch.isfinite(mixed.opacity).all() and bool(((mixed.opacity >= 0) & (mixed.opacity <= 1)).all())
