"""Inference's colour in compiled passes on the CPU (``kernels/colour_network.h``): of packed
samples, the appearance grid's read and the colour network's three layers together, tiles of
samples through each layer (``compiled_ray_colour``); with deferred colour, each sample's
features composited into its ray (``compiled_ray_features``) and each ray shaded from its mean
features, the three layers in a matrix product's register blocks (``compiled_shade``).

Through PyTorch the same colour is a compiled read of the grid, then three products (oneDNN's,
in bfloat16 where the CPU has it) with passes over memory between them: conversions, ReLU,
the per-ray rows gathered. Here no sample's features or hidden values leave the caches.

It applies on the CPU, to a float32 field, where a C compiler is found, for the network
``GridAppearance`` builds (three layers, ``COMPILED_WIDTH`` wide) over a grid whose channels
are whole vectors; elsewhere the colour is PyTorch's (``GridAppearance.ray_colour``), which
computes the same sums (tests/test_compiled_colour.py). On a CPU with AVX512-BF16 the two wide
layers multiply in bfloat16, as oneDNN's products do there (``colour_precision``).

Example (where a C compiler is found):
    >>> import torch
    >>> from nerf_backend.core.scene_bounds import SceneBounds
    >>> from nerf_backend.fields.grid_field import GridField, GridFieldConfig
    >>> field = GridField(GridFieldConfig(initial_resolution=16, resolution=16), SceneBounds((-1.0,) * 3, (1.0,) * 3))
    >>> directions = torch.nn.functional.normalize(torch.randn(4, 3), dim=1)
    >>> colour = compiled_ray_colour(field, directions, torch.bfloat16)
    >>> points, ray = torch.rand(10, 3) * 2 - 1, torch.randint(0, 4, (10,))
    >>> colour is None or bool(torch.allclose(colour(points, ray), field.colour(points, directions[ray]), atol=2e-2))
    True
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor, nn

from ..core.field_functions import RayColourFn
from ..core.tensor_keys import kept_derived
from .compiled_grid import CHANNEL_BLOCK, KernelComponent, compiled_grid_library, kernel_components, rows_in_place

# colour_network.h's HIDDEN: a network of another width colours through PyTorch.
COMPILED_WIDTH = 64


class _ColourNetwork(ctypes.Structure):
    _fields_ = [("grid", KernelComponent * 3), ("per_ray", ctypes.c_void_p), ("w1", ctypes.c_void_p),
                ("w2", ctypes.c_void_p), ("b2", ctypes.c_void_p), ("w3", ctypes.c_void_p), ("b3", ctypes.c_void_p),
                ("box_min", ctypes.c_float * 3), ("scale", ctypes.c_float * 3), ("features", ctypes.c_int32),
                ("hidden", ctypes.c_int32), ("half_plane", ctypes.c_void_p * 3), ("half_line", ctypes.c_void_p * 3)]


def _linear_layers(network: nn.Sequential) -> list[nn.Linear] | None:
    """The network's three layers where it is ``Linear, ReLU, Linear, ReLU, Linear`` of the
    compiled width, ending in 3 colours; else None."""
    kinds = [type(layer) for layer in network]
    if kinds != [nn.Linear, nn.ReLU, nn.Linear, nn.ReLU, nn.Linear]:
        return None
    first, second, third = network[0], network[2], network[4]
    if (first.out_features, second.in_features, second.out_features, third.in_features, third.out_features) != (
            COMPILED_WIDTH,) * 4 + (3,) or any(layer.bias is None for layer in (first, second, third)):
        return None
    return [first, second, third]


def _grid_network(field) -> tuple[_ColourNetwork, list[Tensor]]:
    """The pass's structure with ``field``'s appearance grid and box filled in (the network's
    weights left to the caller), and the grid's row tables it points into (keep them alive)."""
    grid = field.appearance_grid
    with torch.no_grad():
        tables = [rows_in_place(p) for pair in zip(grid.planes, grid.lines) for p in pair]
        box_min = field.box_min.float().tolist()
        scale = (2.0 / (field.box_max - field.box_min).float()).tolist()
    network = _ColourNetwork()
    network.grid = kernel_components([grid], tables, None, None, None, None)
    network.box_min = (ctypes.c_float * 3)(*box_min)
    network.scale = (ctypes.c_float * 3)(*scale)
    network.features, network.hidden = grid.out_dims, COMPILED_WIDTH
    return network, tables


class CompiledRayColour:
    """A ``RayColourFn`` for rays of ``directions``: ``colour(x [P, 3], ray [P]) -> [P, 3]``,
    computed by the compiled pass. Holds the tensors the pass reads."""

    def __init__(self, field, directions: Tensor, layers: list[nn.Linear], library: ctypes.CDLL) -> None:
        _, second, third = layers
        with torch.no_grad():
            per_ray, grid_weight = field.first_layer_parts(directions)
            self._kept = [
                per_ray.contiguous(), grid_weight.contiguous(),
                second.weight.t().contiguous(), second.bias.detach().contiguous(),
                third.weight.detach().contiguous(), third.bias.detach().contiguous(),
            ]
        network, self._tables = _grid_network(field)
        (network.per_ray, network.w1, network.w2, network.b2, network.w3,
         network.b3) = [tensor.data_ptr() for tensor in self._kept]
        self._network = network
        self._library = library

    def __call__(self, x: Tensor, ray: Tensor) -> Tensor:
        x = x.float().contiguous()
        ray = ray.to(torch.int64).contiguous()
        rgb = x.new_empty((x.shape[0], 3))
        if x.shape[0]:
            status = self._library.colour_samples(
                ctypes.byref(self._network), ctypes.c_void_p(x.data_ptr()), ctypes.c_void_p(ray.data_ptr()),
                ctypes.c_int64(x.shape[0]), ctypes.c_void_p(rgb.data_ptr()), ctypes.c_int64(torch.get_num_threads()))
            if status != 0:  # compiled_ray_colour keeps every call within the pass's limits
                raise RuntimeError(f"colour_network.h refused the call (status {status})")
        return rgb


class CompiledRayFeatures:
    """Deferred colour's ``RayColourFn`` for inference: packed samples' appearance features
    ``[P, F]`` (``GridAppearance.ray_features``), and ``composite`` adding each sample's
    weighted features into its ray's row in one compiled pass (no ``[P, F]`` tensor)."""

    def __init__(self, field, library: ctypes.CDLL) -> None:
        self._field = field
        self._network, self._tables = _grid_network(field)  # the network's weights unused
        self._halves = _half_tables(field, self._tables) if library.half_tables() else None
        if self._halves is not None:  # plane, line of each component, as the tables are
            self._network.half_plane = (ctypes.c_void_p * 3)(*[t.data_ptr() for t in self._halves[0::2]])
            self._network.half_line = (ctypes.c_void_p * 3)(*[t.data_ptr() for t in self._halves[1::2]])
        self._library = library
        self.channels = field.appearance_grid.out_dims

    @torch.no_grad()
    def __call__(self, x: Tensor, ray: Tensor) -> Tensor:
        return self._field.appearance_grid(self._field.normalise(x)).float()

    def composite(self, x: Tensor, ray: Tensor, weight: Tensor, out: Tensor, fresh: bool = False) -> None:
        """``out[ray] += weight · features(x)`` for samples whose ``ray`` ascends; ``out [R, F]``
        float32 and contiguous. With ``fresh``, every sample of each ray in ``ray`` is in this
        call and no other: its row is set to their sum (what it held is not read), and rows
        of rays not in ``ray`` are left as they are."""
        x, ray, weight = x.float().contiguous(), ray.to(torch.int64).contiguous(), weight.float().contiguous()
        status = self._library.composite_samples(
            ctypes.byref(self._network), ctypes.c_void_p(x.data_ptr()), ctypes.c_void_p(ray.data_ptr()),
            ctypes.c_void_p(weight.data_ptr()), ctypes.c_int64(x.shape[0]), ctypes.c_void_p(out.data_ptr()),
            ctypes.c_int64(torch.get_num_threads()), ctypes.c_int32(fresh))
        if status != 0:  # compiled_ray_features only builds it for a grid the pass reads
            raise RuntimeError(f"colour_network.h refused the call (status {status})")


def _half_tables(field, tables: list[Tensor]) -> list[Tensor] | None:
    """The appearance grid's row tables in half precision, for ``composite_samples`` to read
    (half the bytes: lego's thirty-minute grid is 44 MB in float32, more than the L3 of the
    project's 2-core EPYCs); kept on ``field`` until its values change, as a view's ten chunks
    each build a ``CompiledRayFeatures``. None where a value is not a finite half."""
    def build() -> list[Tensor] | None:
        halves = [table.to(torch.float16) for table in tables]  # past the range: inf; NaN stays NaN
        return halves if all(bool(torch.isfinite(half).all()) for half in halves) else None
    return kept_derived(field, "half tables", tables, build)


def compiled_ray_features(field) -> CompiledRayFeatures | None:
    """The compiled compositing of ``field``'s appearance features (a ``GridAppearance``), or
    None where it does not apply (not on the CPU in float32, channels not whole vectors, no C
    compiler)."""
    grid = field.appearance_grid
    if grid.channels % CHANNEL_BLOCK or any(p.dtype != torch.float32 or p.device.type != "cpu"
                                            for p in grid.parameters()):
        return None
    library = compiled_grid_library()
    if library is None:
        return None
    library.composite_samples.restype = ctypes.c_int
    library.half_tables.restype = ctypes.c_int
    return CompiledRayFeatures(field, library)


class _ShadeNetwork(ctypes.Structure):
    _fields_ = [("w1", ctypes.c_void_p), ("b1", ctypes.c_void_p), ("w2", ctypes.c_void_p), ("b2", ctypes.c_void_p),
                ("w3", ctypes.c_void_p), ("b3", ctypes.c_void_p), ("features", ctypes.c_int32),
                ("bands", ctypes.c_int32), ("hidden", ctypes.c_int32)]


# colour_network.h's MAX_BANDS and MAX_FEATURES: a direction encoding of more bands, or more
# features a ray, shade through PyTorch.
MAX_SHADE_BANDS = 8
MAX_SHADE_FEATURES = 1024


class CompiledShade:
    """Deferred colour's ``ShadeFn`` at inference, with ``shade_rays`` doing the whole of
    ``volume_rendering.shade_rays`` in one compiled pass (``kernels/colour_network.h``): the
    network's weights as they are when it is made (the appearance basis folded into the first
    layer), in float32."""

    def __init__(self, field, layers: list[nn.Linear], library: ctypes.CDLL) -> None:
        first, second, third = layers
        appearance = field.config.appearance_dims
        with torch.no_grad():
            self._kept = [torch.cat([field.folded_grid_weight(), first.weight[:, appearance:].t()]).contiguous(),
                          first.bias.detach().contiguous(), second.weight.t().contiguous(),
                          second.bias.detach().contiguous(), third.weight.detach().contiguous(),
                          third.bias.detach().contiguous()]
        network = _ShadeNetwork()
        network.w1, network.b1, network.w2, network.b2, network.w3, network.b3 = [t.data_ptr() for t in self._kept]
        network.features = field.appearance_grid.out_dims
        network.bands = field.direction_encoding.num_frequencies
        network.hidden = COMPILED_WIDTH
        self._network, self._library, self._features = network, library, network.features

    def __call__(self, mean: Tensor, directions: Tensor) -> Tensor:
        ones = mean.new_ones(mean.shape[0])
        return self.shade_rays(mean, ones, ones, directions, torch.arange(mean.shape[0]))

    def shade_rays(self, accumulated: Tensor, coloured_weight: Tensor, weight: Tensor, directions: Tensor,
                   shaded: Tensor) -> Tensor:
        """``[R, 3]``: for each ray of ``shaded`` (indices, int64), ``weight`` times the colour of
        ``accumulated / coloured_weight`` seen along its direction; 0 for the other rays."""
        accumulated, coloured_weight, weight, directions = (
            t.float().contiguous() for t in (accumulated, coloured_weight, weight, directions))
        if accumulated.shape[1] != self._features:
            raise ValueError(f"shade_rays: {accumulated.shape[1]} features a ray, the network takes {self._features}")
        shaded = shaded.to(torch.int64).contiguous()
        rgb = accumulated.new_zeros((accumulated.shape[0], 3))
        if shaded.numel():
            status = self._library.shade_rays(
                ctypes.byref(self._network), *(ctypes.c_void_p(t.data_ptr()) for t in (
                    accumulated, coloured_weight, weight, directions, shaded)),
                ctypes.c_int64(shaded.numel()), ctypes.c_void_p(rgb.data_ptr()),
                ctypes.c_int64(torch.get_num_threads()))
            if status != 0:  # compiled_shade only builds it for a network the pass takes
                raise RuntimeError(f"colour_network.h refused the call (status {status})")
        return rgb


def _shading_layers(field) -> list[nn.Linear] | None:
    """The colour network's layers where the compiled shading takes ``field`` (a
    ``GridAppearance`` whose network takes the basis's features and the direction's encoding):
    three layers of the compiled width, the encoding's bands and the features within the
    pass's limits, parameters float32 on the CPU; else None."""
    layers = _linear_layers(field.colour_mlp)
    first = field.colour_mlp[0]
    if (layers is None or not field.config.view_dependent
            or field.direction_encoding.num_frequencies > MAX_SHADE_BANDS
            or first.in_features != field.config.appearance_dims + field.direction_encoding.out_dims
            or field.appearance_grid.out_dims > MAX_SHADE_FEATURES
            or any(p.dtype != torch.float32 or p.device.type != "cpu" for p in field.parameters())):
        return None
    return layers


def compiled_shade(field) -> CompiledShade | None:
    """The compiled deferred shading of ``field`` at inference, or None where it does not apply
    (``_shading_layers``; no C compiler). Kept on ``field`` until the network's or the basis's
    values change: a view's ten chunks each ask for it, and folding the basis into the first
    layer again took lego's views 5 ms each."""
    layers = _shading_layers(field)
    library = compiled_grid_library() if layers is not None else None
    if library is None:
        return None
    library.shade_rays.restype = ctypes.c_int
    weights = [*field.colour_mlp.parameters(), *field.appearance_basis.parameters()]
    return kept_derived(field, "compiled shade", weights, lambda: CompiledShade(field, layers, library))


class _ShadeTrainingNetwork(ctypes.Structure):
    _fields_ = [(name, ctypes.c_void_p) for name in ("basis_t", "basis", "w1_t", "w1_a", "b1", "w2_t", "w2", "b2",
                                                    "w3", "b3")] + [
        (name, ctypes.c_int32) for name in ("features", "fpad", "apad", "bands", "hidden")]


class _ShadeWeights(ctypes.Structure):
    _fields_ = [(name, ctypes.c_void_p) for name in ("basis", "w1", "b1", "w2", "b2", "w3", "b3")] + [
        (name, ctypes.c_int32) for name in ("appearance", "features", "encoding", "bands")]


# colour_network.h's MAX_APAD: a basis of more outputs trains through PyTorch.
MAX_TRAINING_BASIS = 64
# The floats b3's gradient takes in the kernel's sums (colour_network.h's B3_FLOATS).
_B3_FLOATS = 16


class _ShadeRaysTrainingFunction(torch.autograd.Function):
    """``volume_rendering.shade_rays`` in training as one autograd node: the rays' mean features
    gathered, the network, the colours weighted and scattered, forward and backward each one
    compiled call (``CompiledShadeTraining.shade_rays``)."""

    @staticmethod
    def forward(ctx, accumulated, coloured_weight, weight, directions, shaded, basis, w1, b1, w2, b2, w3, b3,
                shader):  # noqa: D102 (autograd's)
        network, kept = shader.network(basis, w1, b1, w2, b2, w3, b3)
        coloured_weight, weight = (t.detach().float().contiguous() for t in (coloured_weight, weight))
        shaded = shaded.to(torch.int64).contiguous()
        rgb, rows = shader.forward_pass(network, accumulated, coloured_weight, weight, directions, shaded)
        ctx.save_for_backward(coloured_weight, weight, shaded, *rows)
        ctx.network, ctx.kept, ctx.shader, ctx.rays = network, kept, shader, accumulated.shape[0]
        return rgb

    @staticmethod
    def backward(ctx, grad_rgb):  # noqa: D102 (autograd's)
        coloured_weight, weight, shaded, *rows = ctx.saved_tensors
        network, shader = ctx.network, ctx.shader
        features, apad = network.features, network.apad
        grad_accumulated, grad_coloured_weight, grad_weight, sums = shader.backward_pass(
            network, coloured_weight, weight, shaded, rows, grad_rgb, ctx.rays)
        inputs, hidden, appearance = apad + shader.encoding, COMPILED_WIDTH, shader.appearance
        parts, at = [], 0
        for part in (inputs * hidden, hidden, hidden * hidden, hidden, 3 * hidden, _B3_FLOATS, features * apad):
            parts.append(sums[at:at + part])
            at += part
        g_w1_t, g_b1, g_w2_t, g_b2, g_w3, g_b3, g_basis_t = parts
        g_w1_t = g_w1_t.view(inputs, hidden)
        g_w1 = torch.cat([g_w1_t[:appearance], g_w1_t[apad:]]).t()
        return (grad_accumulated, grad_coloured_weight, grad_weight, None, None,
                g_basis_t.view(features, apad)[:, :appearance].t(), g_w1, g_b1, g_w2_t.view(hidden, hidden).t(), g_b2,
                g_w3.view(3, hidden), g_b3[:3], None)


class CompiledShadeTraining:
    """Deferred colour's ``ShadeFn`` in training on the CPU: ``GridAppearance``'s basis and
    network over each ray's mean features, forward and backward each one compiled call
    (``kernels/colour_network.h``), in float32; the gradients those of PyTorch's autograd over
    the same operations (tests/test_compiled_colour.py)."""

    def __init__(self, field, library: ctypes.CDLL) -> None:
        self._field, self.library = field, library
        self.appearance = field.config.appearance_dims
        self.encoding = field.direction_encoding.out_dims
        self._bands = field.direction_encoding.num_frequencies

    def __call__(self, mean: Tensor, directions: Tensor) -> Tensor:
        ones = mean.new_ones(mean.shape[0])
        return self.shade_rays(mean, ones, ones, directions, torch.arange(mean.shape[0]))

    def shade_rays(self, accumulated: Tensor, coloured_weight: Tensor, weight: Tensor, directions: Tensor,
                   shaded: Tensor) -> Tensor:
        """``[R, 3]``: for each ray of ``shaded`` (indices), ``weight`` times the colour of
        ``accumulated / coloured_weight`` seen along its direction, 0 for the other rays; one
        autograd node, its gradients those of PyTorch's operations (tests/test_compiled_colour.py)."""
        if accumulated.shape[1] != self._field.appearance_grid.out_dims:
            raise ValueError(f"shade_rays: {accumulated.shape[1]} features a ray, the network takes "
                             f"{self._field.appearance_grid.out_dims}")
        field = self._field
        first, second, third = field.colour_mlp[0], field.colour_mlp[2], field.colour_mlp[4]
        return _ShadeRaysTrainingFunction.apply(accumulated, coloured_weight, weight, directions, shaded,
                                                field.appearance_basis.weight, first.weight, first.bias,
                                                second.weight, second.bias, third.weight, third.bias, self)

    def forward_pass(self, network: _ShadeTrainingNetwork, accumulated: Tensor, coloured_weight: Tensor,
                     weight: Tensor, directions: Tensor, shaded: Tensor) -> tuple[Tensor, tuple[Tensor, ...]]:
        """The compiled forward over ``network`` (``network()``'s): ``rgb [R, 3]`` and the rows its
        backward reads (each shaded ray's mean features, layer inputs, two hidden layers and
        colour, in one allocation); ``shaded`` int64, the others float32."""
        accumulated, coloured_weight, weight, directions = (
            t.detach().float().contiguous() for t in (accumulated, coloured_weight, weight, directions))
        count = shaded.numel()
        widths = (network.features, network.apad + self.encoding, COMPILED_WIDTH, COMPILED_WIDTH, 3)
        rows = tuple(part.view(count, width) for part, width in
                     zip(accumulated.new_empty(count * sum(widths)).split([count * w for w in widths]), widths))
        rgb = accumulated.new_zeros((accumulated.shape[0], 3))
        self.call("shade_rays_training_forward", ctypes.byref(network), accumulated, coloured_weight, weight,
                  directions, shaded, ctypes.c_int64(count), *rows, rgb, ctypes.c_int64(torch.get_num_threads()))
        return rgb, rows

    def backward_pass(self, network: _ShadeTrainingNetwork, coloured_weight: Tensor, weight: Tensor, shaded: Tensor,
                      rows: tuple[Tensor, ...], grad_rgb: Tensor, rays: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The compiled backward from ``grad_rgb [rays, 3]`` over ``forward_pass``'s rows: the
        gradients of the accumulated features, of both weights (the kernel writes them whole,
        zeros included), and the parameters' summed gradients in the kernel's layout."""
        threads = torch.get_num_threads()
        size = int(self.library.shade_training_gradient_floats(ctypes.byref(network)))
        mean = rows[0]
        sums, scratch = mean.new_zeros(size), mean.new_empty(max(threads - 1, 1) * size)
        grad_accumulated, grad_coloured_weight = mean.new_empty((rays, network.features)), mean.new_empty(rays)
        grad_weight = mean.new_empty(rays)
        self.call("shade_rays_training_backward", ctypes.byref(network), coloured_weight, weight, shaded,
                  ctypes.c_int64(shaded.numel()), ctypes.c_int64(rays), *rows, grad_rgb.float().contiguous(), sums,
                  scratch, grad_accumulated, grad_coloured_weight, grad_weight, ctypes.c_int64(threads))
        return grad_accumulated, grad_coloured_weight, grad_weight, sums

    def network(self, basis: Tensor, w1: Tensor, b1: Tensor, w2: Tensor, b2: Tensor, w3: Tensor,
                b3: Tensor) -> tuple[_ShadeTrainingNetwork, list[Tensor]]:
        """The kernel's structure over this step's weights, padded and transposed as it reads
        them (``shade_training_prepare``), and the tensors it points into (keep them alive)."""
        kept = [t.detach().float().contiguous() for t in (basis, w1, b1, w2, b2, w3, b3)]
        weights = _ShadeWeights(*[t.data_ptr() for t in kept], basis.shape[0], basis.shape[1], self.encoding,
                                self._bands)
        room = kept[0].new_empty(int(self.library.shade_training_room_floats(ctypes.byref(weights))))
        network = _ShadeTrainingNetwork()
        self.library.shade_training_prepare(ctypes.byref(weights), ctypes.c_void_p(room.data_ptr()),
                                            ctypes.byref(network))
        return network, [*kept, room]

    def call(self, name: str, *arguments) -> None:
        converted = [ctypes.c_void_p(a.data_ptr()) if isinstance(a, Tensor) else a for a in arguments]
        status = getattr(self.library, name)(*converted)
        if status != 0:  # compiled_shade_training only builds it for a network the pass takes
            raise RuntimeError(f"colour_network.h refused {name} (status {status})")


def compiled_shade_training(field) -> CompiledShadeTraining | None:
    """Training's compiled deferred shading for ``field``, or None where it does not apply (as
    ``compiled_shade``; and under autocast, whose reduced-precision products are PyTorch's)."""
    if (_shading_layers(field) is None or field.config.appearance_dims > MAX_TRAINING_BASIS
            or torch.is_autocast_enabled("cpu")):
        return None
    library = compiled_grid_library()
    if library is None:
        return None
    for name in ("shade_rays_training_forward", "shade_rays_training_backward"):
        getattr(library, name).restype = ctypes.c_int
    library.shade_training_gradient_floats.restype = ctypes.c_int64
    library.shade_training_room_floats.restype = ctypes.c_int64
    library.shade_training_prepare.restype = None
    return CompiledShadeTraining(field, library)


def colour_precision() -> int | None:
    """The bits of the floats the compiled pass multiplies its two wide layers in: 16
    (bfloat16, a CPU with AVX512-BF16) or 32; None where the pass is not built."""
    library = compiled_grid_library()
    return None if library is None else int(library.colour_precision())


def compiled_ray_colour(field, directions: Tensor, dtype: torch.dtype = torch.float32) -> RayColourFn | None:
    """The compiled colour pass for ``field`` (a ``GridAppearance`` whose network takes the grid's
    features and the direction's encoding) and rays of ``directions``, where its products are
    as precise as ``dtype`` or more (a pass in bfloat16 only where ``dtype`` is bfloat16); None
    where it does not apply (see the module's notes)."""
    grid = field.appearance_grid
    layers = _linear_layers(field.colour_mlp)
    if (layers is None or directions.device.type != "cpu" or grid.channels % CHANNEL_BLOCK
            or any(p.dtype != torch.float32 or p.device.type != "cpu" for p in field.parameters())):
        return None
    library = compiled_grid_library()
    if library is None or (colour_precision() == 16 and dtype != torch.bfloat16):
        return None
    library.colour_samples.restype = ctypes.c_int
    return CompiledRayColour(field, directions, layers, library)
