"""A mesh cut into charts and packed into one texture's square (a UV atlas), by xatlas (the
Python binding of Jonathan Young's xatlas, the unwrapper Godot and many engines use: charts
that follow the surface's creases, packed with a gutter between them), not a packer written
here.

Example:
    >>> import torch
    >>> vertices = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # a tetrahedron
    >>> atlas = unwrap(vertices, faces, texture_size=64)
    >>> atlas.faces.shape, bool(atlas.uv.min() >= 0 and atlas.uv.max() <= 1)
    (torch.Size([4, 3]), True)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import xatlas
from torch import Tensor

# Texels between charts: the bake spreads each chart's colours this far past its border, so
# bilinear filtering (and the first mip levels) near a seam never read a neighbour's colours.
GUTTER_TEXELS = 4


@dataclass
class UvAtlas:
    source_vertex: Tensor  # [V'] int64: the input vertex each atlas vertex copies (seams split vertices)
    faces: Tensor  # [F, 3] int64 into the atlas vertices, the input's faces in the same order
    uv: Tensor  # [V', 2] in [0, 1], v = 0 at the texture's top row (glTF's convention)


def unwrap(vertices: Tensor, faces: Tensor, texture_size: int) -> UvAtlas:
    """Charts of ``faces [F, 3]`` over ``vertices [V, 3]`` packed into a ``texture_size``
    square with ``GUTTER_TEXELS`` between charts."""
    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices.float().numpy(), faces.numpy().astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = texture_size
    pack.padding = GUTTER_TEXELS
    pack.bilinear = True
    atlas.generate(xatlas.ChartOptions(), pack)
    source_vertex, atlas_faces, uv = atlas[0]
    return UvAtlas(torch.from_numpy(source_vertex.astype(np.int64)), torch.from_numpy(atlas_faces.astype(np.int64)),
                   torch.from_numpy(uv.astype(np.float32)))
