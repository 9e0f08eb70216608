"""The inference march in one compiled pass per ray, for the CPU (``kernels/march_render.c``).

``render_marched_stopping_early`` marches all rays of a chunk together in rounds of tensor
operations; on the CPU those rounds cost more than the work in them (an 800×800 view of a
bright object: spans, march, density and compositing about 1.2 s of 1.9 s, for 7 M density
reads). Here each ray is marched by a C loop that reads the field's density volume itself and
stops at the ray's surface; it returns the samples to colour, packed, and the colour field
runs once over them in PyTorch. The image is the same as the PyTorch path's to the bounds of
the early stop and the uncoloured faint weight (tests/test_compiled_march.py).

It applies where the density is ``activation(trilinear(volume))`` (``VolumeDensity``: the grid
and surface fields) and the tensors are on the CPU; elsewhere, and where no C compiler is
found, the PyTorch march renders (``compiled_march_library`` says why not).

Example (where a C compiler is found):
    >>> import torch
    >>> from nerf_backend.model_components.occupancy import OccupancyGrid
    >>> library, why_not = compiled_march_library()
    >>> grid = OccupancyGrid(torch.full((3,), -1.0), torch.full((3,), 1.0), cells=8)
    >>> solid = VolumeDensity(torch.full((9, 9, 9), 10.0), "softplus", scale=5.0)  # σ ≈ 50 everywhere
    >>> out = render_marched_compiled(
    ...     torch.tensor([[0.0, -3.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0]]),
    ...     torch.tensor([2.0]), torch.tensor([4.0]), density=solid,
    ...     ray_colour=lambda x, ray: torch.zeros_like(x), occupancy=grid, step=0.05, steps=41,
    ...     background=1.0, library=library)
    >>> round(float(out.opacity), 3), round(float(out.rgb.sum()), 3)  # a black, opaque cube
    (1.0, 0.0)
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator
from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.cameras import Intrinsics, camera_rays, pixel_centres, ray_box_intersection
from ..core.field_functions import RayColourFn, ShadeFn
from ..core.stage_timer import count, stage
from ..kernels.build import kernel_or_note, load_kernel
from .marcher import EXACT_STOP, OPAQUE_TRANSMITTANCE, RayStop, RayValues
from .occupancy import OccupancyGrid
from .render_output import RenderOutput
from .volume_rendering import MIN_SHADED_WEIGHT, shade_rays

ACTIVATIONS = {"softplus": 0, "laplace": 1, "neus": 2}  # march_render.c's ACTIVATION_*
# Packed samples one call of the kernel may write (24 bytes each): bounds the memory of a chunk
# of rays whatever the field (a haze colours every step of every ray).
SAMPLES_PER_CALL = 1 << 20
# Samples the colour field takes at a time. Measured on 2 CPU cores, float32, the 2.0 M coloured
# samples of a bright object's 800×800 view (B800): 8 192 a batch 0.73-0.88 s, 25 000 0.69-0.75
# s, 65 536 0.86-1.42 s, 262 144 1.1-1.3 s (larger batches leave the caches); with the network in
# bfloat16, lego's views: 16 384 0.96-0.98 s a view, 32 768 0.89, 65 536 0.92.
COLOUR_BATCH = 32768
# Rays a render pass gives the compiled march (render_image's chunk): its memory is bounded by
# SAMPLES_PER_CALL rather than by the rays, and a long call lets its threads share the work.
RENDER_CHUNK = 65536


@dataclass(frozen=True)
class VolumeDensity:
    """A density the compiled march can read: ``activation(trilinear(volume))`` over the
    occupancy grid's box, ``volume [Nz, Ny, Nx]`` at the box's vertices (x fastest).

    ``softplus``: σ = scale · softplus(v + shift) (TensoRF's parametrisation);
    ``laplace``: σ = VolSDF's Laplace CDF of the signed distance v with β = scale;
    ``neus``: NeuS's opacity of the march step (β = scale), from v half a step before and after
    the sample along its ray (``SurfaceField.density_along``)."""

    volume: Tensor
    activation: str
    scale: float
    shift: float = 0.0


class _Settings(ctypes.Structure):
    _fields_ = [("step", ctypes.c_float), ("steps", ctypes.c_int64), ("span", ctypes.c_int64),
                ("cells", ctypes.c_int64 * 3), ("vertices", ctypes.c_int64 * 3),
                ("box_min", ctypes.c_float * 3), ("box_max", ctypes.c_float * 3),
                ("activation", ctypes.c_int32), ("a", ctypes.c_float), ("b", ctypes.c_float),
                ("opaque_transmittance", ctypes.c_float), ("skipped_weight", ctypes.c_float)]


def compiled_march_library() -> tuple[ctypes.CDLL | None, str | None]:
    """The built kernel and None, or None and why it is unavailable (said once on stderr: the
    PyTorch march then renders, slower)."""
    library, reason = kernel_or_note("march_render", "rendering through PyTorch's march")
    if library is None:
        return None, reason
    library.march_render.restype = ctypes.c_int64
    library.rays_through_box.restype = None
    library.pixel_rays.restype = None
    return library, None


def pixel_rays(intrinsics: Intrinsics, camera_to_world: Tensor, start: int, stop: int) -> tuple[Tensor, Tensor]:
    """``camera_rays(intrinsics, camera_to_world, pixel_centres(width, arange(start, stop)))``:
    the origins and unit directions of pixels ``start`` to ``stop`` (row-major), on the pose's
    device. On the CPU by ``march_render.c``'s ``pixel_rays`` in one pass (within a float32 step
    or two of PyTorch's: the rotation's sums in another order), elsewhere through PyTorch.

    Example:
        >>> k = Intrinsics(2, 2, 1.0, 1.0, 1.0, 1.0)
        >>> origins, directions = pixel_rays(k, torch.eye(4), 3, 4)  # pixel (1, 1): the centre is (1.5, 1.5)
        >>> [round(v, 4) for v in directions[0].tolist()]
        [0.4082, -0.4082, -0.8165]
    """
    library = compiled_march_library()[0] if camera_to_world.device.type == "cpu" else None
    if library is None:
        pixels = torch.arange(start, stop, device=camera_to_world.device)
        return camera_rays(intrinsics, camera_to_world, pixel_centres(intrinsics.width, pixels))
    pose = camera_to_world.detach().to(torch.float32)
    camera = (ctypes.c_float * 16)(intrinsics.fl_x, intrinsics.fl_y, intrinsics.cx, intrinsics.cy,
                                   *pose[:3, :3].reshape(-1).tolist(), *pose[:3, 3].tolist())
    origins, directions = torch.empty((stop - start, 3)), torch.empty((stop - start, 3))
    library.pixel_rays(camera, ctypes.c_int64(intrinsics.width), ctypes.c_int64(start), ctypes.c_int64(stop - start),
                       _pointer(origins), _pointer(directions))
    return origins, directions


def ray_box_stretch(origins: Tensor, directions: Tensor, box_min: Tensor, box_max: Tensor,
                    within: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """``ray_box_intersection``'s ``t_near [R]`` and ``t_far [R]`` (a miss: ``t_far == t_near``);
    with ``within`` (``t_near``, ``t_far``), that stretch narrowed to the box instead. On the
    CPU in float32 by ``march_render.c``'s ``rays_through_box``, the same operations in one pass
    (through PyTorch about twelve passes, 4-5 ms for a render chunk of 65 536 rays), elsewhere
    by ``ray_box_intersection``.

    Example:
        >>> o, d = torch.tensor([[0.0, 0.0, -3.0], [5.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]] * 2)
        >>> near, far = ray_box_stretch(o, d, -torch.ones(3), torch.ones(3))
        >>> near.tolist(), far.tolist()  # the second ray misses: an empty stretch
        ([2.0, 2.0], [4.0, 2.0])
        >>> [t.tolist() for t in ray_box_stretch(o, d, -torch.ones(3), torch.ones(3), within=(near - 1, far - 1))]
        [[2.0, 2.0], [3.0, 2.0]]
    """
    compiled = origins.device.type == "cpu" and origins.dtype == directions.dtype == torch.float32
    library = compiled_march_library()[0] if compiled else None
    if library is None:
        entry, exit_, _ = ray_box_intersection(origins, directions, box_min, box_max)
        if within is None:
            return entry, exit_
        t_near = torch.maximum(within[0], entry)
        return t_near, torch.maximum(torch.minimum(within[1], exit_), t_near)
    origins, directions = origins.contiguous(), directions.contiguous()
    if within is None:
        t_near, t_far = torch.empty(origins.shape[0]), torch.empty(origins.shape[0])
    else:
        t_near, t_far = (t.to(torch.float32, copy=True).contiguous() for t in within)
    box = (ctypes.c_float * 6)(*box_min.tolist(), *box_max.tolist())
    library.rays_through_box(_pointer(origins), _pointer(directions), ctypes.c_int64(origins.shape[0]), box,
                             _pointer(t_near), _pointer(t_far), ctypes.c_int32(within is not None))
    return t_near, t_far


def _whole_ray_batches(sample_ray: Tensor, start: int, stop: int) -> Iterator[slice]:
    """Slices of ``sample_ray[start:stop]`` (ascending) of about COLOUR_BATCH samples each, none
    splitting a ray's samples: a batch runs on past COLOUR_BATCH to its last ray's end.

    Example:
        >>> [(s.start, s.stop) for s in _whole_ray_batches(torch.tensor([0] * 40000 + [1] * 3), 0, 40003)]
        [(0, 40000), (40000, 40003)]
    """
    first = start
    while first < stop:
        end = min(first + COLOUR_BATCH, stop)
        if end < stop:  # past every sample of the ray at end - 1
            end = first + int(torch.searchsorted(sample_ray[first:stop], sample_ray[end - 1], right=True))
        yield slice(first, end)
        first = end


def _pointer(tensor: Tensor) -> ctypes.c_void_p:
    return ctypes.c_void_p(tensor.data_ptr())


@torch.no_grad()
def render_marched_compiled(
    origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor, *, density: VolumeDensity,
    ray_colour: RayColourFn, occupancy: OccupancyGrid, step: float, steps: int, background: Tensor | float,
    library: ctypes.CDLL, stop: RayStop = EXACT_STOP, shade_fn: ShadeFn | None = None,
) -> RenderOutput:
    """``render_marched_stopping_early``'s image, each ray marched by the compiled kernel: the
    skip grid's spans, then fine steps in occupied cells, the density read from
    ``density.volume``, a ray stopped once its transmittance is under
    ``stop.opaque_transmittance``, and up to ``stop.skipped_weight`` of its faintest weight
    left to its mean colour; with ``shade_fn``, ``ray_colour`` gives appearance features, shaded
    once a ray (deferred colour, ``shade_rays``)."""
    rays = origins.shape[0]
    as_float = {"dtype": torch.float32}
    origins, directions = origins.to(**as_float).contiguous(), directions.to(**as_float).contiguous()
    t_near, t_far = t_near.to(**as_float).contiguous(), t_far.to(**as_float).contiguous()
    skip, occupied = occupancy.skip_bricks(), occupancy.occupied_bricks()
    volume = density.volume.to(**as_float).contiguous()
    settings = _Settings(
        step=step, steps=steps, span=occupancy.skip_span_steps(step), cells=(ctypes.c_int64 * 3)(*occupancy.cells),
        vertices=(ctypes.c_int64 * 3)(volume.shape[2], volume.shape[1], volume.shape[0]),
        box_min=(ctypes.c_float * 3)(*occupancy.box_min.tolist()),
        box_max=(ctypes.c_float * 3)(*occupancy.box_max.tolist()),
        activation=ACTIVATIONS[density.activation], a=density.scale, b=density.shift,
        opaque_transmittance=stop.opaque_transmittance, skipped_weight=stop.skipped_weight)
    per_ray = torch.zeros((4, rays), **as_float)  # transmittance, depth, skipped, coloured weight
    done = torch.zeros(rays, dtype=torch.uint8)
    counters = torch.zeros(2, dtype=torch.int64)
    threads = torch.get_num_threads()
    # Each call packs at most SAMPLES_PER_CALL samples (any one ray fits a thread's region);
    # the rays left undone go to the next call, so memory is bounded whatever the field.
    region = max(steps, SAMPLES_PER_CALL // threads)
    sample_ray = torch.empty(threads * region, dtype=torch.int64)
    sample_position = torch.empty((threads * region, 3), **as_float)
    sample_weight = torch.empty(threads * region, **as_float)
    written = torch.zeros(threads, dtype=torch.int64)
    # Σ w·colour (or features) of the coloured samples; a ray's samples come in one batch
    composited = RayValues(origins, rays, whole_rays=True)
    pending: Tensor | None = None  # the rays still to march (None: all)
    while pending is None or pending.numel() > 0:
        with stage("march", items=lambda: int(counters[0])):
            counters.zero_()
            library.march_render(
                ctypes.byref(settings), _pointer(origins), _pointer(directions), _pointer(t_near), _pointer(t_far),
                _pointer(skip), _pointer(occupied), _pointer(volume),
                None if pending is None else _pointer(pending),
                ctypes.c_int64(rays if pending is None else pending.numel()), ctypes.c_int64(threads), _pointer(per_ray[0]), _pointer(per_ray[1]), _pointer(per_ray[2]),
                _pointer(per_ray[3]), _pointer(done), ctypes.c_int64(region), _pointer(sample_ray),
                _pointer(sample_position), _pointer(sample_weight), _pointer(written), _pointer(counters))
            kept = written.tolist()
        with stage("colour", items=sum(kept)):
            for thread, kept_count in enumerate(kept):
                for part in _whole_ray_batches(sample_ray, thread * region, thread * region + kept_count):
                    composited.add_weighted(ray_colour, sample_position[part], sample_ray[part], sample_weight[part])
        pending = (done == 0).nonzero().squeeze(1)
    transmittance, depth, skipped, coloured_weight = per_ray
    # The skipped weight takes the coloured samples' weighted mean colour; a ray with none keeps it black.
    with stage("shade", items=lambda: int((coloured_weight > MIN_SHADED_WEIGHT).sum())):
        rgb = shade_rays(composited.values, coloured_weight, coloured_weight + skipped, directions, shade_fn)
    return RenderOutput(rgb=rgb + transmittance[:, None] * background, depth=depth, opacity=1.0 - transmittance,
                        weights=None, t_edges=None)


# The training march looks up blocks of 2^3 = 8 cells a side, then the cells' bits: at 255³ cells
# a byte a cell (16 MB) left the caches and each step waited on memory (lego at 800×800: 45 ns a
# step, 20 ms for 1 024 rays on one core).
TRAIN_BLOCK_SHIFT = 3
_kept = [torch.empty(0, dtype=torch.int64), torch.empty(0), torch.empty(0)]
# train_march.h's RECORD_WIDTH: a lit sample's midpoint, length, density pre-activation and point.
RECORD_WIDTH = 6
# bench-step's count of the rays the compiled training march marched (its density pass is inside).
COMPILED_TRAINING_MARCH = "compiled training march"


def _scratch(size: int, record: bool) -> tuple[Tensor, Tensor, Tensor | None]:
    """Room for ``size`` sample indices, weights and (``record``) records, kept between steps:
    fresh megabytes each step cost more than the march (the kernel's pages are zeroed on first
    touch)."""
    if _kept[0].numel() < size:
        _kept[:2] = [torch.empty(size, dtype=torch.int64), torch.empty(size)]
    if record and _kept[2].shape[0] < size:
        _kept[2] = torch.empty((size, RECORD_WIDTH))
    return _kept[0][:size], _kept[1][:size], _kept[2][:size] if record else None


class _TrainMarch(ctypes.Structure):
    _fields_ = [("step", ctypes.c_float), ("steps", ctypes.c_int64), ("cells", ctypes.c_int64 * 3),
                ("box_min", ctypes.c_float * 3), ("box_max", ctypes.c_float * 3), ("density_scale", ctypes.c_float),
                ("density_shift", ctypes.c_float), ("density_gain", ctypes.c_float),
                ("opaque_transmittance", ctypes.c_float),
                ("block_shift", ctypes.c_int64), ("blocks", ctypes.c_int64 * 3)]


@dataclass(frozen=True)
class GridDensity:
    """A density the compiled training march reads: ``scale · softplus(Σ features + shift)`` of
    a factorised grid over the occupancy grid's box (``compiled_grid.density_components``)."""

    components: object  # the kernel's three components (a ctypes array)
    tables: list  # the tensors they point into, kept alive
    scale: float
    shift: float
    gain = 1.0
    kernel = "vm_grid"  # the kernel whose march_train reads it


@dataclass(frozen=True)
class SparseDensity:
    """A density the compiled training march reads: ``scale · softplus(gain · v + shift)`` of a
    sparse voxel grid's density channel (``SparseVoxelGrid``, its first channel)."""

    components: object  # a pointer to the grid as sparse_grid.c reads it
    grid: object  # the SparseVoxelGrid, kept alive
    scale: float
    shift: float
    gain: float
    kernel = "sparse_grid"

    @classmethod
    def of(cls, grid, scale: float, shift: float, gain: float) -> "SparseDensity | None":
        """The grid's density, or None where the kernel cannot read it (not on the CPU in
        float32, no C compiler)."""
        values = grid.values
        if values.device.type != "cpu" or values.dtype != torch.float32 or load_kernel("sparse_grid")[0] is None:
            return None
        return cls(ctypes.pointer(grid.kernel_view()), grid, scale, shift, gain)


def compiled_lit_samples(occupancy: OccupancyGrid, step: float, steps: int, density: GridDensity | SparseDensity,
                         record: bool = False):
    """A ``LitSamplesFn`` (core/field_functions.py) for ``render_marched``: the training march's
    lit samples and their weights (without gradients) found by ``kernels/train_march.h``'s
    ``march_train`` (built into the density's kernel) in one pass a ray, where
    ``marcher.occupied_samples`` and ``lit_samples`` build tensors of every step of every ray
    (lego at 800×800: 254 steps a ray, 1 in 10 occupied). The same samples, up to float rounding
    at cell borders (tests/test_compiled_grid.py, tests/test_sparse_grid.py). With ``record``,
    a third output ``[L, RECORD_WIDTH]``: each sample's midpoint and length along its ray, the
    density's pre-activation there and the point in [-1, 1] of the occupancy's box (what the
    grid field's compiled lit pass takes: ``compiled_lit_pass.py``)."""
    library = load_kernel(density.kernel)[0]
    library.march_train.restype = ctypes.c_int64
    settings = _TrainMarch(step=step, steps=steps, cells=(ctypes.c_int64 * 3)(*occupancy.cells),
                           box_min=(ctypes.c_float * 3)(*occupancy.box_min.tolist()),
                           box_max=(ctypes.c_float * 3)(*occupancy.box_max.tolist()),
                           density_scale=density.scale, density_shift=density.shift, density_gain=density.gain,
                           opaque_transmittance=OPAQUE_TRANSMITTANCE, block_shift=TRAIN_BLOCK_SHIFT)
    occupied = occupancy.occupied_bricks()
    blocks = occupancy.occupied_blocks(1 << TRAIN_BLOCK_SHIFT).contiguous().view(torch.uint8)
    settings.blocks = (ctypes.c_int64 * 3)(*blocks.shape)

    def lit(origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor, offset: Tensor) -> Tensor:
        rays = origins.shape[0]
        found, weights, records = _scratch(rays * steps, record)
        reads = ctypes.c_int64(0)
        inputs = [t.float().contiguous() for t in (origins, directions, t_near, t_far, offset)]
        lit_count = library.march_train(ctypes.byref(settings), *[_pointer(t) for t in inputs], ctypes.c_int64(rays),
                                    _pointer(occupied), _pointer(blocks), density.components, _pointer(found),
                                    _pointer(weights), None if records is None else _pointer(records),
                                    ctypes.byref(reads),
                                    ctypes.c_int64(torch.get_num_threads()))
        if lit_count < 0:
            raise RuntimeError(f"{density.kernel}.c's march_train refused the density grid")
        with stage("density pass", items=reads.value):  # done inside the march; its reads counted here
            pass
        count(COMPILED_TRAINING_MARCH, rays)
        if records is not None:
            return found[:lit_count].clone(), weights[:lit_count].clone(), records[:lit_count].clone()
        return found[:lit_count].clone(), weights[:lit_count].clone()

    return lit
