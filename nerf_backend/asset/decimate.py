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
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from torch import Tensor

from ..core.errors import NerfError

# Simplifier passes at most: measured, a second pass always reached the budget.
MAX_PASSES = 4


def decimate(vertices: Tensor, faces: Tensor, triangles: int) -> tuple[Tensor, Tensor]:
    """``vertices [V, 3]`` and ``faces [F, 3]`` collapsed to at most ``triangles`` faces
    (unchanged when already within it); vertices no face uses are dropped.

    One pass of the simplifier stops short of a large reduction on a surface of many open pieces
    (a young field's floaters: 3.4 M faces in 1 500 pieces came to 2 406 for a budget of 2 000),
    so it runs again on its own result while that still shrinks; what is then still over the
    budget loses its pieces of least area, smallest first."""
    if triangles < 4:
        raise NerfError(f"a triangle budget of {triangles}: at least 4 triangles (a closed surface)")
    if len(faces) <= triangles:
        return vertices, faces
    points, kept = vertices.double().numpy(), faces.numpy().astype(np.int64)
    for _ in range(MAX_PASSES):
        before = len(kept)
        points, kept = fast_simplification.simplify(points, kept, target_count=triangles)
        if len(kept) <= triangles or len(kept) >= before:
            break
    if len(kept) > triangles:
        kept = _largest_pieces(points, kept, triangles)
    used = np.unique(kept)
    remap = np.full(len(points), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return (torch.from_numpy(np.ascontiguousarray(points[used])).to(vertices.dtype),
            torch.from_numpy(remap[kept]))


def _largest_pieces(points: np.ndarray, faces: np.ndarray, triangles: int) -> np.ndarray:
    """The faces of the connected pieces of largest area that fit in ``triangles`` together
    (the largest piece, cut to the budget, where even it alone does not)."""
    count = len(points)
    edges = sparse.coo_matrix((np.ones(2 * len(faces)), (faces[:, [0, 1]].reshape(-1), faces[:, [1, 2]].reshape(-1))),
                              shape=(count, count))
    _, piece_of_vertex = connected_components(edges, directed=False)
    piece = piece_of_vertex[faces[:, 0]]
    corners = points[faces]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    piece_area = np.bincount(piece, weights=area)
    piece_faces = np.bincount(piece)
    order = np.argsort(-piece_area, kind="stable")
    fits = np.cumsum(piece_faces[order]) <= triangles
    kept_pieces = order[fits] if fits[0] else order[:1]
    kept = faces[np.isin(piece, kept_pieces)]
    return kept[:triangles]


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """Unit normals ``[V, 3]``: each vertex's faces' normals weighted by their areas (faces
    counter-clockwise seen from outside, so the normals point out)."""
    a, b, c = vertices[faces].unbind(dim=1)
    face_normals = torch.cross(b - a, c - a, dim=1)  # length: twice the area
    normals = torch.zeros_like(vertices).index_add_(0, faces.reshape(-1), face_normals.repeat_interleave(3, dim=0))
    return torch.nn.functional.normalize(normals, dim=1)
