"""A mesh's texture space, in plain tensor maths: which triangle covers each texel of a UV
atlas (and where inside it), and colours spread past each chart's border so that filtering
near a seam reads no background.

Texel ``(row, column)`` of an ``S``-texel side has its centre at ``u = (column + 0.5) / S``,
``v = (row + 0.5) / S``: row 0 is ``v`` near 0, as glTF's texture coordinates have it (their
origin is the image's top-left corner).

Example:
    >>> import torch
    >>> uv = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    >>> cover = rasterise_uv(uv, torch.tensor([[0, 1, 2]]), 4)
    >>> (cover.face >= 0).int().tolist()  # the lower-left half, diagonal included
    [[1, 1, 1, 1], [1, 1, 1, 0], [1, 1, 0, 0], [1, 0, 0, 0]]
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# A texel centre on a triangle's edge belongs to it: a small tolerance in barycentric units, so
# that the texels along a seam between two triangles of one chart are never left to neither.
EDGE_TOLERANCE = 1e-6


@dataclass
class TexelCover:
    face: Tensor  # [S, S] int64: the triangle each texel centre lies in, -1 where none
    barycentric: Tensor  # [S, S, 3]: its weights of the triangle's three corners (0 where none)


def rasterise_uv(uv: Tensor, faces: Tensor, size: int) -> TexelCover:
    """The triangle ``faces [F, 3]`` (corners indexing ``uv [V, 2]`` in [0, 1]) that covers
    each texel centre of a ``size``-texel square texture, and the texel's barycentric weights.
    Where triangles overlap (they should not in an atlas), the later one wins.

    Each triangle tests only the texels of its bounding box: an atlas's triangles are small, so
    that is a few texels each, enumerated for all triangles at once."""
    corners = uv[faces].double() * size - 0.5  # [F, 3, 2] in texel-centre units (centres on integers)
    low = corners.amin(dim=1).ceil().clamp(0, size - 1).long()  # [F, 2] (u, v)
    high = corners.amax(dim=1).floor().clamp(0, size - 1).long()
    extent = (high - low + 1).clamp_min(0)  # a triangle between two centres covers none
    count = extent[:, 0] * extent[:, 1]
    face = torch.repeat_interleave(torch.arange(len(faces)), count)
    # The k-th texel of a triangle's box, row by row.
    k = torch.arange(int(count.sum())) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
    width = extent[face, 0]
    column = low[face, 0] + k % width.clamp_min(1)
    row = low[face, 1] + k // width.clamp_min(1)
    weights = _barycentric(corners[face], torch.stack([column, row], dim=1).double())
    inside = (weights >= -EDGE_TOLERANCE).all(dim=1)
    face, row, column, weights = face[inside], row[inside], column[inside], weights[inside]
    texel_face = torch.full((size, size), -1, dtype=torch.int64)
    texel_weights = torch.zeros((size, size, 3), dtype=uv.dtype)
    texel_face[row, column] = face
    texel_weights[row, column] = weights.clamp_min(0).to(uv.dtype)
    return TexelCover(texel_face, texel_weights)


def _barycentric(triangles: Tensor, points: Tensor) -> Tensor:
    """Weights ``[P, 3]`` of ``points [P, 2]`` in ``triangles [P, 3, 2]`` (a degenerate
    triangle gives weights that fail every inside test)."""
    a, b, c = triangles.unbind(dim=1)
    v0, v1, v2 = b - a, c - a, points - a
    denominator = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    safe = torch.where(denominator.abs() > 1e-12, denominator, torch.full_like(denominator, float("nan")))
    w1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / safe
    w2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / safe
    weights = torch.stack([1.0 - w1 - w2, w1, w2], dim=1)
    return torch.nan_to_num(weights, nan=-1.0)


def dilate(image: Tensor, filled: Tensor, texels: int) -> Tensor:
    """``image [S, S, C]`` with its unfilled texels (``filled [S, S]`` False) given the mean of
    their filled neighbours (8-connected), ``texels`` rings outward: a chart's colours reach
    past its border, so bilinear filtering and mipmaps at a seam blend chart colours only.

    Example:
        >>> import torch
        >>> image = torch.zeros(1, 4, 1); image[0, 0, 0] = 1.0
        >>> filled = torch.tensor([[True, False, False, False]])
        >>> dilate(image, filled, 2)[0, :, 0].tolist()
        [1.0, 1.0, 1.0, 0.0]
    """
    image, filled = image.clone(), filled.clone()
    for _ in range(texels):
        weight = filled.to(image.dtype)
        total = _neighbour_sum(image * weight[..., None])
        count = _neighbour_sum(weight[..., None])
        grow = ~filled & (count[..., 0] > 0)
        image[grow] = total[grow] / count[grow]
        filled |= grow
    return image


def _neighbour_sum(values: Tensor) -> Tensor:
    """The sum over each texel's 8 neighbours of ``values [S, S, C]`` (zero beyond the edge)."""
    padded = torch.nn.functional.pad(values.permute(2, 0, 1), (1, 1, 1, 1))
    height, width = values.shape[:2]
    total = torch.zeros_like(values.permute(2, 0, 1))
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy != 1 or dx != 1:
                total += padded[:, dy:dy + height, dx:dx + width]
    return total.permute(1, 2, 0)
