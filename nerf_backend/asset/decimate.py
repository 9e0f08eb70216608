"""A mesh reduced to a triangle budget by quadric edge collapse (Garland and Heckbert), with
``fast_simplification`` (pyvista's binding of Sven Forstmann's Fast-Quadric-Mesh-Simplification:
a small wheel on every platform users have, numpy in and out), and its normals.

Example:
    >>> import torch
    >>> from skimage.measure import marching_cubes
    >>> axis = torch.linspace(-1, 1, 40)
    >>> ball = (torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij")).norm(dim=0) - 0.7).numpy()
    >>> vertices, faces, _, _ = marching_cubes(ball, 0.0)
    >>> small_vertices, small_faces = decimate(torch.from_numpy(vertices.copy()), torch.from_numpy(faces.copy()), 500)
    >>> len(small_faces) <= 500 < len(faces)
    True
"""

from __future__ import annotations

import fast_simplification
import numpy as np
import torch
from torch import Tensor

from ..core.errors import NerfError


def decimate(vertices: Tensor, faces: Tensor, triangles: int) -> tuple[Tensor, Tensor]:
    """``vertices [V, 3]`` and ``faces [F, 3]`` collapsed to at most ``triangles`` faces
    (unchanged when already within it); vertices no face uses are dropped."""
    if triangles < 4:
        raise NerfError(f"a triangle budget of {triangles}: at least 4 triangles (a closed surface)")
    if len(faces) <= triangles:
        return vertices, faces
    points, kept = fast_simplification.simplify(vertices.double().numpy(), faces.numpy().astype(np.int64),
                                                target_count=triangles)
    used = np.unique(kept)
    remap = np.full(len(points), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return (torch.from_numpy(np.ascontiguousarray(points[used])).to(vertices.dtype),
            torch.from_numpy(remap[kept]))


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """Unit normals ``[V, 3]``: each vertex's faces' normals weighted by their areas (faces
    counter-clockwise seen from outside, so the normals point out)."""
    a, b, c = vertices[faces].unbind(dim=1)
    face_normals = torch.cross(b - a, c - a, dim=1)  # length: twice the area
    normals = torch.zeros_like(vertices).index_add_(0, faces.reshape(-1), face_normals.repeat_interleave(3, dim=0))
    return torch.nn.functional.normalize(normals, dim=1)
