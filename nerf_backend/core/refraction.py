"""Rays against triangles, and light at a smooth dielectric surface: the maths of seeing through
glass whose shape and index of refraction Blender knows (``model_components/glass.py``).

Pure torch and numpy, no I/O: Möller-Trumbore's ray-triangle test (on any device), the bounding
volume hierarchy that kernels/ray_mesh.c walks on the CPU, Snell's law and the exact
(unpolarised) Fresnel reflectance.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

# Ray-triangle tests in one pass: rays × triangles (float32, about 60 bytes a test at its peak: 30 MB).
_TESTS_PER_CHUNK = 1 << 19


def nearest_triangle_hits(origins: Tensor, directions: Tensor, corners: Tensor,
                          t_min: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """Each ray's nearest crossing of any triangle beyond ``t_min`` (Möller-Trumbore, both
    sides): ``t [R]`` (inf where it crosses none), the triangle's index ``[R]`` (-1 there) and
    the crossing's barycentric weights ``[R, 3]`` of the triangle's corners.

    ``corners [T, 3, 3]``: each triangle's three corners.

    Example:
        >>> corners = torch.tensor([[[0.0, 0, 1], [1, 0, 1], [0, 1, 1]]])
        >>> t, face, weights = nearest_triangle_hits(torch.tensor([[0.25, 0.25, 0.0], [2.0, 2, 0]]),
        ...                                          torch.tensor([[0.0, 0, 1], [0, 0, 1]]), corners)
        >>> t.tolist(), face.tolist(), weights[0].tolist()
        ([1.0, inf], [0, -1], [0.5, 0.25, 0.25])
    """
    count = origins.shape[0]
    best_t = origins.new_full((count,), float("inf"))
    best_face = torch.full((count,), -1, dtype=torch.long, device=origins.device)
    best_uv = origins.new_zeros((count, 2))
    if count == 0 or corners.shape[0] == 0:
        return best_t, best_face, _weights(best_uv)
    v0 = corners[:, 0]
    edge1, edge2 = corners[:, 1] - v0, corners[:, 2] - v0
    chunk = max(1, _TESTS_PER_CHUNK // count)
    for start in range(0, corners.shape[0], chunk):
        e1, e2, a = edge1[start:start + chunk], edge2[start:start + chunk], v0[start:start + chunk]
        p = torch.cross(directions[:, None, :], e2[None], dim=-1)  # [R, C, 3]
        det = (e1[None] * p).sum(-1)
        inverse = 1.0 / torch.where(det.abs() > 1e-12, det, torch.ones_like(det))
        s = origins[:, None, :] - a[None]
        u = (s * p).sum(-1) * inverse
        q = torch.cross(s, e1[None].expand_as(s), dim=-1)
        v = (directions[:, None, :] * q).sum(-1) * inverse
        t = (e2[None] * q).sum(-1) * inverse
        valid = (det.abs() > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > t_min)
        t = torch.where(valid, t, torch.full_like(t, float("inf")))
        chunk_t, chunk_face = t.min(dim=1)
        better = chunk_t < best_t
        if bool(better.any()):
            rows = better.nonzero().squeeze(1)
            faces = chunk_face.index_select(0, rows)
            best_t[rows] = chunk_t[rows]
            best_face[rows] = faces + start
            best_uv[rows] = torch.stack([u[rows, faces], v[rows, faces]], dim=1)
    return best_t, best_face, _weights(best_uv)


def _weights(uv: Tensor) -> Tensor:
    return torch.cat([1.0 - uv.sum(dim=1, keepdim=True), uv], dim=1)


def refract(directions: Tensor, normals: Tensor, eta: Tensor) -> tuple[Tensor, Tensor]:
    """Snell's law: unit ``directions [R, 3]`` crossing a surface of unit ``normals [R, 3]``
    (either side), from a medium of index n1 into one of n2, ``eta = n1 / n2 [R]``. Returns
    the refracted unit directions and whether the light is totally reflected instead (then the
    direction is the mirror reflection).

    Example:
        >>> d = torch.tensor([[0.6, 0.0, -0.8]])  # 36.87° from the normal
        >>> out, total = refract(d, torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([1.0 / 1.5]))
        >>> round(float(out[0, 0]) * 1.5, 6), bool(total[0])  # sin θ2 · n2 = sin θ1 · n1
        (0.6, False)
        >>> steep = torch.tensor([[0.8, 0.0, -0.6]])  # leaving glass at 53°, past its critical angle (41.8°)
        >>> refract(steep, torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([1.5]))[1].tolist()
        [True]
    """
    facing = torch.where(((directions * normals).sum(dim=1, keepdim=True) > 0), -normals, normals)
    cos_i = -(directions * facing).sum(dim=1)
    sin2_t = eta * eta * (1.0 - cos_i * cos_i).clamp(min=0.0)
    total = sin2_t >= 1.0
    cos_t = (1.0 - sin2_t).clamp(min=0.0).sqrt()
    refracted = eta[:, None] * directions + (eta * cos_i - cos_t)[:, None] * facing
    reflected = directions + 2.0 * cos_i[:, None] * facing
    out = torch.where(total[:, None], reflected, refracted)
    return out / out.norm(dim=1, keepdim=True).clamp(min=1e-12), total


def reflect(directions: Tensor, normals: Tensor) -> Tensor:
    """The mirror reflection of ``directions [R, 3]`` about unit ``normals [R, 3]`` (either side).

    Example:
        >>> reflect(torch.tensor([[0.6, 0.0, -0.8]]), torch.tensor([[0.0, 0.0, 1.0]])).tolist()
        [[0.6000000238418579, 0.0, 0.800000011920929]]
    """
    return directions - 2.0 * (directions * normals).sum(dim=1, keepdim=True) * normals


def fresnel_reflectance(directions: Tensor, normals: Tensor, eta: Tensor) -> Tensor:
    """The share of unpolarised light a smooth dielectric reflects ``[R]`` (exact Fresnel), for
    light along ``directions`` meeting the surface from a medium of index n1 into n2
    (``eta = n1 / n2``); 1 past the critical angle.

    Example:
        >>> head_on = fresnel_reflectance(torch.tensor([[0.0, 0, -1]]), torch.tensor([[0.0, 0, 1]]),
        ...                               torch.tensor([1 / 1.5]))
        >>> round(float(head_on[0]), 4)  # ((n2 - n1) / (n2 + n1))², glass in air
        0.04
    """
    cos_i = (directions * normals).sum(dim=1).abs().clamp(max=1.0)
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    cos_t = (1.0 - sin2_t).clamp(min=0.0).sqrt()
    # rs and rp with n1 = eta, n2 = 1 (only their ratio counts)
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t).clamp(min=1e-12)
    rp = (eta * cos_t - cos_i) / (eta * cos_t + cos_i).clamp(min=1e-12)
    return torch.where(sin2_t >= 1.0, torch.ones_like(cos_i), 0.5 * (rs * rs + rp * rp))


# Triangles a leaf of ``build_bvh``'s hierarchy holds at most.
BVH_LEAF_SIZE = 4


def build_bvh(corners: np.ndarray, leaf_size: int = BVH_LEAF_SIZE) -> tuple[np.ndarray, ...]:
    """A bounding volume hierarchy over triangles ``corners [T, 3, 3]``, split at the median of
    their centres along the widest axis: ``lo``, ``hi [N, 3]`` float32 (each node's bounds),
    ``child [N, 2]`` int32 (an inner node's children; a leaf's ``-(first + 1), count`` in the
    reordered triangles) and ``order [T]`` (the reordered triangles' indices in ``corners``).
    The root is node 0 (kernels/ray_mesh.c walks it).

    Example:
        >>> corners = np.stack([np.eye(3) + shift for shift in range(10)]).astype(np.float32)
        >>> lo, hi, child, order = build_bvh(corners, leaf_size=4)
        >>> child.tolist()[:3], sorted(order.tolist()) == list(range(10))
        ([[1, 4], [2, 3], [-1, 2]], True)
    """
    lower, upper, centres = corners.min(axis=1), corners.max(axis=1), corners.mean(axis=1)
    lo, hi, child, order = [], [], [], []

    def build(indices: np.ndarray) -> int:
        node = len(child)
        lo.append(lower[indices].min(axis=0))
        hi.append(upper[indices].max(axis=0))
        child.append((0, 0))
        if len(indices) <= leaf_size:
            child[node] = (-(len(order) + 1), len(indices))
            order.extend(indices.tolist())
            return node
        spread = centres[indices]
        axis = int(np.argmax(spread.max(axis=0) - spread.min(axis=0)))
        half = len(indices) // 2
        ranked = indices[np.argpartition(spread[:, axis], half)]
        first = build(ranked[:half])
        child[node] = (first, build(ranked[half:]))
        return node

    build(np.arange(len(corners)))
    return (np.asarray(lo, np.float32).reshape(-1, 3), np.asarray(hi, np.float32).reshape(-1, 3),
            np.asarray(child, np.int32).reshape(-1, 2), np.asarray(order, np.int64))
