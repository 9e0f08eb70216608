"""The NeRF's colour baked into a texture: each texel's point on the surface, coloured by the
field as the training cameras that face it saw it.

A NeRF's colour holds the scene's lighting, and may depend on the viewing direction. The
texture holds one colour a texel: the field's colour at the texel's surface point, averaged
over the ``VIEWS_PER_TEXEL`` training cameras that face the surface there most squarely,
weighted by how squarely (the cosine between the surface normal and the direction to the
camera). A diffuse surface bakes to its colour as the images show it; a highlight that moves
with the viewer bakes to its average over those views; a texel no training camera faces takes
the colour seen head-on (along the normal). Occlusion is not tested: the field gives a colour
at any point for any direction, and cameras behind other geometry see the same field.

Example:
    >>> import torch
    >>> from nerf_backend.asset.texture_space import TexelCover
    >>> vertices = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> normals = torch.tensor([[0.0, 0, 1]]).expand(3, 3)
    >>> cover = TexelCover(torch.tensor([[0, -1]]), torch.tensor([[[0.2, 0.3, 0.5], [0, 0, 0]]]))
    >>> above = torch.tensor([[0.0, 0.0, 5.0]])  # one camera, looking down at the triangle
    >>> colour_fn = lambda x, d: torch.cat([x[:, :2], -d[:, 2:]], dim=1)  # (x, y, cosine)
    >>> texture = bake_texels(colour_fn, vertices, normals, torch.tensor([[0, 1, 2]]), cover, above)
    >>> [round(value, 3) for value in texture.colours[0, 0].tolist()], texture.filled.tolist()
    ([0.3, 0.5, 0.993], [[True, False]])
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.field_functions import ColourFn
from .texture_space import TexelCover

VIEWS_PER_TEXEL = 8
# A camera faces a point when the direction to it is within this cosine of the normal's side.
MIN_FACING = 0.05


@dataclass
class BakedTexels:
    colours: Tensor  # [S, S, 3] in [0, 1]; 0 where no triangle covers the texel
    filled: Tensor  # [S, S] bool: a triangle covers the texel


@torch.no_grad()
def bake_texels(colour_fn: ColourFn, vertices: Tensor, normals: Tensor, faces: Tensor, cover: TexelCover,
                camera_centres: Tensor,
                chunk: int = 32768, device: torch.device | str = "cpu") -> BakedTexels:
    """The field's colour (``colour_fn(points [P, 3], directions [P, 3]) -> [P, 3]``, directions
    from the camera to the point) at every covered texel's surface point, as the module says.
    ``vertices``/``normals [V, 3]`` and ``faces [F, 3]``: the atlas's mesh (in the frame
    ``colour_fn`` and ``camera_centres [C, 3]`` are in); ``cover``: which face and where each
    texel lies."""
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
        colours = colour_fn(points[:, None, :].expand(-1, views, -1).reshape(-1, 3), directions.reshape(-1, 3))
        colours = colours.float().view(-1, views, 3)
        texel_colours[start:start + chunk] = ((weight[..., None] * colours).sum(dim=1)
                                              / weight.sum(dim=1, keepdim=True)).clamp(0, 1).cpu()
    image = torch.zeros((*cover.face.shape, 3))
    image[filled] = texel_colours
    return BakedTexels(image, filled)
