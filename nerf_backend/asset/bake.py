"""The NeRF's colour baked into a texture: each texel's point on the surface, coloured as the
training cameras that face it saw it rendered.

A NeRF's colour holds the scene's lighting, and may depend on the viewing direction. Its
image is an integral along each ray, and the colour a point holds need not be that integral:
a surface field's weights spread a cell or two about the zero level, and the colour grid is
free to differ across that spread as long as the integral is right (on A.blend the field's
colour at the zero level was 8 % darker than its own render, and the asset baked from it 3 dB
under the NeRF). So a texel takes what the model renders: along the ray from each chosen
camera through the texel's point, over the stretch of it within ``reach`` either side of the
point, divided by the opacity gathered there (``colour_seen_near``). The stretch keeps other
objects along the ray out; a camera whose weight along it lies mostly before the point sees
another surface there (a cube's side, for a point near its edge) and does not count.

The cameras: the ``VIEWS_PER_TEXEL`` training cameras that face the surface there most
squarely, weighted by how squarely (the cosine between the surface normal and the direction
to the camera). A diffuse surface bakes to its colour as the images show it; a highlight that
moves with the viewer bakes to its average over those views; a texel no training camera
faces, or none sees, takes the colour seen head-on (along the normal) or what the facing
cameras render there.

Example (a field whose colour is the point's own position, seen by every camera):
    >>> import torch
    >>> from nerf_backend.asset.texture_space import TexelCover
    >>> vertices = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> normals = torch.tensor([[0.0, 0, 1]]).expand(3, 3)
    >>> cover = TexelCover(torch.tensor([[0, -1]]), torch.tensor([[[0.2, 0.3, 0.5], [0, 0, 0]]]))
    >>> above = torch.tensor([[0.0, 0.0, 5.0]])  # one camera, looking down at the triangle
    >>> seen_fn = lambda x, d: (torch.cat([x[:, :2], -d[:, 2:]], dim=1), torch.ones(len(x), dtype=torch.bool))
    >>> texture = bake_texels(seen_fn, vertices, normals, torch.tensor([[0, 1, 2]]), cover, above)
    >>> [round(value, 3) for value in texture.colours[0, 0].tolist()], texture.filled.tolist()
    ([0.3, 0.5, 0.993], [[True, False]])
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.field_functions import RenderFn, SeenColourFn
from .texture_space import TexelCover

VIEWS_PER_TEXEL = 8
# A camera faces a point when the direction to it is within this cosine of the normal's side.
MIN_FACING = 0.05
# A stretch of ray that gathers less opacity than this passes by the surface: nothing is seen.
MIN_OPACITY = 0.05


@dataclass
class BakedTexels:
    colours: Tensor  # [S, S, 3] in [0, 1]; 0 where no triangle covers the texel
    filled: Tensor  # [S, S] bool: a triangle covers the texel


def colour_seen_near(render: RenderFn, reach: float) -> SeenColourFn:
    """What ``render`` shows of each point looking along its direction: the colour it renders
    over the stretch of that ray from ``reach`` before the point to ``reach`` past it, over the
    opacity gathered there; seen where that stretch gathers at least ``MIN_OPACITY`` and the
    centre of its weight lies less than half the reach before the point (else the camera sees
    some other surface in front of it).

    Example (an opaque red wall at z = 0, rays looking down the z axis):
        >>> import torch
        >>> def wall(origins, directions, t_near, t_far):
        ...     crossing = -origins[:, 2] / directions[:, 2]  # where each ray meets z = 0
        ...     hit = ((crossing >= t_near) & (crossing <= t_far)).float()
        ...     return torch.tensor([1.0, 0, 0]) * hit[:, None], hit, crossing * hit
        >>> seen = colour_seen_near(wall, reach=0.1)
        >>> down = torch.tensor([[0.0, 0, -1]]).expand(3, 3)
        >>> colour, visible = seen(torch.tensor([[0.0, 0, 0.02], [0, 0, 0.5], [0, 0, -0.08]]), down)
        >>> colour[0].tolist(), visible.tolist()  # on the wall; far above it; under it
        ([1.0, 0.0, 0.0], [True, False, False])
    """
    def seen(points: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        start = torch.zeros(len(points), dtype=points.dtype, device=points.device)
        rgb, opacity, depth = render(points - reach * directions, directions, start, start + 2 * reach)
        held = opacity.clamp_min(1e-6)
        colour = (rgb / held[:, None]).clamp(0, 1)
        centre = depth / held  # from the stretch's start: the point lies at ``reach``
        return colour, (opacity >= MIN_OPACITY) & (centre > reach / 2)
    return seen


@torch.no_grad()
def bake_texels(seen_fn: SeenColourFn, vertices: Tensor, normals: Tensor, faces: Tensor, cover: TexelCover,
                camera_centres: Tensor,
                chunk: int = 32768, device: torch.device | str = "cpu") -> BakedTexels:
    """The colour ``seen_fn(points [P, 3], directions [P, 3]) -> (colours [P, 3], seen [P])``
    gives (directions from the camera to the point) at every covered texel's surface point, as
    the module says. ``vertices``/``normals [V, 3]`` and ``faces [F, 3]``: the atlas's mesh (in
    the frame ``seen_fn`` and ``camera_centres [C, 3]`` are in); ``cover``: which face and where
    each texel lies."""
    filled = cover.face >= 0
    corner_vertices = faces[cover.face[filled]]  # [T, 3]
    weights = cover.barycentric[filled].to(vertices.dtype)  # [T, 3]
    texel_colours = torch.zeros((len(corner_vertices), 3))
    centres = camera_centres.to(device=device, dtype=torch.float32)
    views = min(VIEWS_PER_TEXEL, len(centres))
    for start in range(0, len(corner_vertices), chunk):
        corners = corner_vertices[start:start + chunk]
        w = weights[start:start + chunk, :, None]
        points = (w * vertices[corners]).sum(dim=1).to(device=device, dtype=torch.float32)  # [P, 3]
        normal = torch.nn.functional.normalize((w * normals[corners]).sum(dim=1), dim=1).to(points)
        to_point = torch.nn.functional.normalize(points[:, None, :] - centres[None, :, :], dim=2)  # [P, C, 3]
        facing = -(to_point * normal[:, None, :]).sum(dim=2)  # cosine of normal and direction to camera
        facing, camera = facing.topk(views, dim=1)
        directions = to_point.gather(1, camera[..., None].expand(-1, -1, 3))  # [P, K, 3]
        weight = facing.clamp_min(0) * (facing > MIN_FACING)
        # Faced by no camera: seen head-on, along the inward normal.
        unseen = weight.sum(dim=1) == 0
        directions[unseen, 0] = -normal[unseen]
        weight[unseen, 0] = 1.0
        colours, seen = seen_fn(points[:, None, :].expand(-1, views, -1).reshape(-1, 3), directions.reshape(-1, 3))
        colours = colours.float().view(-1, views, 3)
        # Only the cameras that see the point, where any does.
        seen_weight = weight * seen.view(-1, views)
        weight = torch.where(seen_weight.sum(dim=1, keepdim=True) > 0, seen_weight, weight)
        texel_colours[start:start + chunk] = ((weight[..., None] * colours).sum(dim=1)
                                              / weight.sum(dim=1, keepdim=True)).clamp(0, 1).cpu()
    image = torch.zeros((*cover.face.shape, 3))
    image[filled] = texel_colours
    return BakedTexels(image, filled)
