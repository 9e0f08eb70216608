"""Which way the scene's true surface faces, from its mesh (``scene_geometry.ply``): the
normals a reflection-aware colour reflects the view about (Ref-NeRF learns them; Blender knows
them).

``corner_normals`` shades a welded mesh as Blender's auto smooth does: each corner of a face
takes the area-weighted mean of the normals of the faces around its vertex that turn by less
than ``smooth_angle`` from its own, so a UV sphere is smooth and a cube keeps flat faces.
``normal_volume`` samples the shaded surface into the cells of a grid (each cell the mean of the
normals in it, spread a few cells off the surface), to be read trilinearly at any point.

Example:
    >>> import numpy as np
    >>> vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    >>> faces = np.array([[0, 2, 1], [0, 1, 3]])  # two faces meeting at a right angle
    >>> corner_normals(vertices, faces)[0].round(3).tolist()  # flat: 90° is past the smooth angle
    [[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]
    >>> corner_normals(vertices, faces, smooth_angle_deg=100.0)[0, 0].round(3).tolist()  # smoothed
    [0.0, -0.707, -0.707]
"""

from __future__ import annotations

import math

import numpy as np

# Blender's default auto smooth angle: faces turning by less than this share their corners' normals.
SMOOTH_ANGLE_DEG = 30.0
# Samples per cell edge on each triangle, so that every cell a triangle crosses gets samples.
_SAMPLES_PER_CELL = 2


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``[T, 3]``: each face's normal (right-hand winding) scaled by twice its area."""
    corners = vertices[faces]
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def corner_normals(vertices: np.ndarray, faces: np.ndarray, smooth_angle_deg: float = SMOOTH_ANGLE_DEG) -> np.ndarray:
    """``[T, 3, 3]`` unit normals at each face's corners (auto smooth; see the module)."""
    weighted = face_normals(vertices, faces)
    unit = weighted / np.maximum(np.linalg.norm(weighted, axis=1, keepdims=True), 1e-30)
    corner_vertex = faces.reshape(-1)
    corner_face = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(corner_vertex, kind="stable")
    sorted_vertex = corner_vertex[order]
    starts = np.searchsorted(sorted_vertex, sorted_vertex, side="left")
    sizes = np.searchsorted(sorted_vertex, sorted_vertex, side="right") - starts
    # Every pair of corners at the same vertex: Σ over vertices of (corners there)².
    first = np.repeat(np.arange(len(order)), sizes)
    within = np.arange(len(first)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    second = np.repeat(starts, sizes) + within
    face_a, face_b = corner_face[order[first]], corner_face[order[second]]
    close = (unit[face_a] * unit[face_b]).sum(axis=1) >= math.cos(math.radians(smooth_angle_deg)) - 1e-9
    summed = np.zeros((len(order), 3))
    np.add.at(summed, first[close], weighted[face_b[close]])
    normals = np.empty((len(order), 3))
    normals[order] = summed
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    return normals.reshape(-1, 3, 3)


def normal_volume(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, box_min: np.ndarray,
                  cell_size: float, shape: tuple[int, int, int], spread_cells: int = 2) -> np.ndarray:
    """``[nx, ny, nz, 3]`` float32: the unit normal of the surface in each cell of the grid
    (cubes of ``cell_size`` from ``box_min``), from ``corner_normals``' ``normals`` interpolated
    over each face; zero where no surface passes within ``spread_cells`` cells (a cell off the
    surface takes the mean of its neighbours', so a sample a cell or two from the surface
    reads the nearest surface's normal).

    Example:
        >>> import numpy as np
        >>> square = np.array([[0, 0, 0.6], [1, 0, 0.6], [1, 1, 0.6], [0, 1, 0.6]], np.float64)
        >>> faces = np.array([[0, 1, 2], [0, 2, 3]])
        >>> volume = normal_volume(square, faces, corner_normals(square, faces), np.zeros(3), 0.25, (4, 4, 4), 1)
        >>> volume[1, 2, 2].tolist(), volume[1, 2, 1].tolist(), volume[1, 2, 0].tolist()  # on it, beside it, off it
        ([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    """
    sums = np.zeros((*shape, 3))
    for chosen, weights in _surface_samples(vertices[faces], cell_size):
        points = np.einsum("sk,tkc->tsc", weights, vertices[faces][chosen]).reshape(-1, 3)
        shaded = np.einsum("sk,tkc->tsc", weights, normals[chosen]).reshape(-1, 3)
        cells = np.floor((points - box_min) / cell_size).astype(np.int64)
        inside = ((cells >= 0) & (cells < np.asarray(shape))).all(axis=1)
        np.add.at(sums, tuple(cells[inside].T), shaded[inside])
    for _ in range(spread_cells):
        empty = ~sums.any(axis=3)
        around = np.zeros_like(sums)
        for axis in range(3):
            for shift in (1, -1):
                around += _shifted(sums / np.maximum(np.linalg.norm(sums, axis=3, keepdims=True), 1e-30), axis, shift)
        sums[empty] = around[empty]
    length = np.linalg.norm(sums, axis=3, keepdims=True)
    return np.where(length > 1e-12, sums / np.maximum(length, 1e-30), 0.0).astype(np.float32)


def surface_cells(corners: np.ndarray, box_min: np.ndarray, cell_size: float, shape: tuple[int, int, int],
                  grow_cells: int = 0) -> np.ndarray:
    """``[nx, ny, nz]`` bool: the cells of the grid (cubes of ``cell_size`` from ``box_min``)
    that triangles ``corners [T, 3, 3]`` pass through, grown by ``grow_cells`` cells each way.

    Example:
        >>> import numpy as np
        >>> square = np.array([[[0, 0, 0.6], [1, 0, 0.6], [1, 1, 0.6]]], np.float64)
        >>> marked = surface_cells(square, np.zeros(3), 0.25, (4, 4, 4))
        >>> int(marked.sum()), bool(marked[3, 0, 2]), bool(marked[0, 3, 2])  # the half below the diagonal
        (10, True, False)
    """
    marked = np.zeros(shape, bool)
    for chosen, weights in _surface_samples(corners, cell_size):
        points = np.einsum("sk,tkc->tsc", weights, corners[chosen]).reshape(-1, 3)
        cells = np.floor((points - box_min) / cell_size).astype(np.int64)
        inside = ((cells >= 0) & (cells < np.asarray(shape))).all(axis=1)
        marked[tuple(cells[inside].T)] = True
    for _ in range(grow_cells):
        grown = marked.copy()
        for axis in range(3):
            for shift in (1, -1):
                grown |= _shifted(marked, axis, shift)
        marked = grown
    return marked


def _surface_samples(corners: np.ndarray, cell_size: float):
    """Barycentric samples of triangles ``corners [T, 3, 3]``, ``_SAMPLES_PER_CELL`` along a
    cell's edge so that every cell a triangle crosses gets some: ``(chosen [T] bool, weights
    [S, 3])`` for each group of triangles sampled alike."""
    edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    counts = np.floor(edges / cell_size * _SAMPLES_PER_CELL).astype(np.int64) + 1
    for n in np.unique(counts):
        a, b = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = a + b <= n
        yield counts == n, np.stack([1.0 - (a[keep] + b[keep]) / n, a[keep] / n, b[keep] / n], axis=1)


def _shifted(values: np.ndarray, axis: int, shift: int) -> np.ndarray:
    """``values`` moved by ``shift`` cells along ``axis``, zeros where nothing moved in."""
    out = np.zeros_like(values)
    length = values.shape[axis]
    to, source = [slice(None)] * values.ndim, [slice(None)] * values.ndim
    to[axis] = slice(shift, None) if shift > 0 else slice(None, length + shift)
    source[axis] = slice(None, length - shift) if shift > 0 else slice(-shift, None)
    out[tuple(to)] = values[tuple(source)]
    return out
