"""The functions of a field that marchers, mesh extraction and baking are given (nerfacc's
style: the caller passes the field as functions, and the algorithm knows nothing else of it).
Every point is in world space; every function returns float values, one row a point."""

from __future__ import annotations

from typing import Callable

from torch import Tensor

# density(points [P, 3]) -> [P]
DensityFn = Callable[[Tensor], Tensor]
# density(points [P, 3], directions [P, 3]) -> [P] of samples seen along those directions: what
# marchers read (a surface field's NeuS opacity depends on the direction; other fields ignore it).
SampleDensityFn = Callable[[Tensor, Tensor], Tensor]
# colour(points [P, 3], directions [P, 3]) -> [P, 3]: each point seen along its own direction.
ColourFn = Callable[[Tensor, Tensor], Tensor]
# field(points [P, 3], directions [P, 3]) -> (density [P], colour [P, 3]) in one call.
FieldFn = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
# render(origins [R, 3], directions [R, 3] (unit), t_near [R], t_far [R]) -> (Σ w·c [R, 3] over no
# background, opacity Σ w [R], Σ w·t [R]): what a model renders along each stretch of ray.
RenderFn = Callable[[Tensor, Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]
# seen(points [P, 3], directions [P, 3]) -> (colour [P, 3], seen [P] bool): each point's colour as
# a camera looking along its direction sees it, and whether that camera sees that point at all.
SeenColourFn = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
# colour(points [P, 3], ray [P]) -> [P, 3] of samples packed from a batch of rays: ``ray`` indexes
# the rays the function was made for (``MarchableField.ray_colour(directions)``), so work that
# is the same for every sample of a ray is done once a ray.
RayColourFn = Callable[[Tensor, Tensor], Tensor]
# shade(features [R, C], directions [R, 3]) -> [R, 3]: deferred colour (SNeRG's idea): a ray's
# colour from its samples' appearance features composited along it (their weighted mean), seen
# along the ray's direction: the colour network runs once a ray, not once a sample. A ShadeFn may
# also have ``shade_rays(accumulated [R, C], coloured_weight [R], weight [R], directions [R, 3],
# shaded [S]) -> [R, 3]``, doing ``volume_rendering.shade_rays``' whole work at once (the grid
# field's compiled pass at inference: field_components/compiled_colour.py's CompiledShade).
ShadeFn = Callable[[Tensor, Tensor], Tensor]
# lit(origins [R, 3], directions [R, 3], t_near [R], t_far [R], offset [R, 1]) -> (flat indices [L]
# (ray · steps + step) of a training march's samples in occupied cells that light still reaches,
# sorted by ray, then along it; their weights [L] without gradients): a march that finds them in
# one compiled pass (the grid field's).
LitSamplesFn = Callable[[Tensor, Tensor, Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]
# field(points [P, 3], directions [P, 3], coloured [C]) -> (density [P], colour [C, 3]): a field's
# density at every point and its colour only at the points ``coloured`` indexes.
SparseColourFieldFn = Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]
# lit_pass(lit [L], weight [L], record [L, 6], rays, steps) -> (opacity [R], depth [R], coloured
# weight [R], composited appearance features [R, C], coloured samples): a field's training pass
# with deferred colour over a ``LitSamplesFn``'s samples and their records, in one call (the grid
# field's compiled pass: field_components/compiled_lit_pass.py).
LitPassFn = Callable[[Tensor, Tensor, Tensor, int, int], tuple[Tensor, Tensor, Tensor, Tensor, int]]
