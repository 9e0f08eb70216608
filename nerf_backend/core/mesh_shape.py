"""The shape of a triangle mesh's pieces: which faces make one body, and how thick a body is for
its size (``data.occupancy_prior`` leaves thin-walled glass to the field). Pure numpy."""

from __future__ import annotations

import numpy as np


def wall_share(corners: np.ndarray) -> float:
    """How thick a body of glass is for its size: its mean chord ``4V/S`` (Cauchy's: the mean
    length a random line runs inside it; twice the wall's thickness for a thin shell) over the
    diagonal of its bounding box, from its triangles ``corners [T, 3, 3]`` (a closed mesh: an
    open one has no volume and reads as thin).

    Example:
        >>> cube = np.array([[[0, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 0, 0], [1, 1, 0], [1, 0, 0]],
        ...                  [[0, 0, 1], [1, 0, 1], [1, 1, 1]], [[0, 0, 1], [1, 1, 1], [0, 1, 1]],
        ...                  [[0, 0, 0], [1, 0, 0], [1, 0, 1]], [[0, 0, 0], [1, 0, 1], [0, 0, 1]],
        ...                  [[0, 1, 0], [0, 1, 1], [1, 1, 1]], [[0, 1, 0], [1, 1, 1], [1, 1, 0]],
        ...                  [[0, 0, 0], [0, 0, 1], [0, 1, 1]], [[0, 0, 0], [0, 1, 1], [0, 1, 0]],
        ...                  [[1, 0, 0], [1, 1, 0], [1, 1, 1]], [[1, 0, 0], [1, 1, 1], [1, 0, 1]]], float)
        >>> round(wall_share(cube), 3)  # 4/6 over √3
        0.385
        >>> round(wall_share(cube * [1, 1, 0.02]), 3)  # a pane
        0.027
    """
    corners = np.asarray(corners, dtype=np.float64)
    if not len(corners):
        return 0.0
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    volume = abs(float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum())) / 6.0
    area = float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()) / 2.0
    flat = corners.reshape(-1, 3)
    diagonal = float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))
    return 4.0 * volume / area / diagonal if area > 0 and diagonal > 0 else 0.0


def mesh_bodies(vertices: np.ndarray, faces: np.ndarray) -> list[np.ndarray]:
    """The bodies of a mesh: for each, the indices of its ``faces [T, 3]``. A body is a
    connected piece (faces sharing a vertex) with the pieces inside its bounding box: a hollow
    ball's inner surface, a box's walls modelled as two surfaces, are one body with the outer.

    Example:
        >>> corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0],
        ...                     [0.2, 0.2, 0], [0.4, 0.2, 0], [0.2, 0.4, 0]], float)
        >>> [body.tolist() for body in mesh_bodies(corners, np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]]))]
        [[0, 2], [1]]
    """
    if not len(faces):
        return []
    # Each vertex takes the least label of the faces it is on, then its label's label, until none
    # changes: every piece ends labelled by its least vertex.
    labels = np.arange(int(faces.max()) + 1)
    while True:
        spread = labels.copy()
        np.minimum.at(spread, faces.ravel(), np.repeat(labels[faces].min(axis=1), 3))
        spread = spread[spread]
        if np.array_equal(spread, labels):
            break
        labels = spread
    face_labels = labels[faces[:, 0]]
    order = np.argsort(face_labels, kind="stable")
    pieces = np.split(order, np.flatnonzero(np.diff(face_labels[order])) + 1)
    corners = vertices[faces[order]].reshape(len(order), 9)
    starts = np.concatenate([[0], np.cumsum([len(piece) for piece in pieces])[:-1]])
    low = np.minimum.reduceat(corners.reshape(-1, 3, 3).min(axis=1), starts)
    high = np.maximum.reduceat(corners.reshape(-1, 3, 3).max(axis=1), starts)
    # Largest box first, each piece joins the first kept body whose box holds its own (the
    # test a body at a time in numpy: shattered glass has thousands of pieces).
    owner = np.empty(len(pieces), dtype=np.int64)
    kept_low, kept_high, kept = np.empty_like(low), np.empty_like(high), np.empty(len(pieces), dtype=np.int64)
    count = 0
    for index in np.argsort(-np.prod(high - low, axis=1), kind="stable").tolist():
        holds = ((kept_low[:count] <= low[index]) & (high[index] <= kept_high[:count])).all(axis=1)
        found = int(holds.argmax()) if holds.any() else -1
        if found < 0:
            kept_low[count], kept_high[count], kept[count], found = low[index], high[index], index, count
            count += 1
        owner[index] = kept[found]
    bodies: dict[int, list[np.ndarray]] = {}
    for index, piece in enumerate(pieces):
        bodies.setdefault(int(owner[index]), []).append(piece)
    return sorted((np.sort(np.concatenate(parts)) for parts in bodies.values()), key=lambda body: int(body[0]))
