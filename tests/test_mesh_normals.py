"""The surface's normals from its mesh (nerf_backend/core/mesh_normals.py) against analytic
shapes: a UV sphere's smooth normals radial, a cube's faces flat, and the normal volume's cells
on and near a sphere pointing along its radius."""

from __future__ import annotations

import math

import numpy as np

from nerf_backend.core.mesh_normals import corner_normals, normal_volume


def _uv_sphere(radius: float, segments: int = 64, rings: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """A welded UV sphere (as Blender's, poles included), faces wound outwards."""
    theta = np.linspace(0.0, math.pi, rings + 1)[1:-1]
    phi = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring_points = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    vertices = np.concatenate([[[0, 0, 1]], ring_points, [[0, 0, -1]]]) * radius
    index = lambda ring, seg: 1 + ring * segments + seg % segments  # noqa: E731
    faces = []
    for seg in range(segments):
        faces.append([0, index(0, seg), index(0, seg + 1)])
        for ring in range(rings - 2):
            a, b = index(ring, seg), index(ring, seg + 1)
            c, d = index(ring + 1, seg), index(ring + 1, seg + 1)
            faces += [[a, c, d], [a, d, b]]
        faces.append([len(vertices) - 1, index(rings - 2, seg + 1), index(rings - 2, seg)])
    return vertices, np.array(faces)


def _cube(half: float) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)], float)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    faces = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
    return vertices, faces


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cosine = (a * b).sum(axis=-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def test_a_uv_spheres_corner_normals_are_its_radii():
    """Smooth: every corner's normal within 1° of the radius through its vertex (measured 0.95°
    on the rings beside the poles, where the faces around a vertex differ in size), where its
    faces' own normals are up to 4° off it (flat shading)."""
    vertices, faces = _uv_sphere(0.4)
    normals = corner_normals(vertices, faces)
    radial = vertices[faces]
    assert _angle_deg(normals, radial).max() < 1.0
    flat = corner_normals(vertices, faces, smooth_angle_deg=0.0)
    assert _angle_deg(flat, radial).max() > 2.0
    assert np.allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-9)


def test_a_cubes_faces_stay_flat():
    """Faces meeting at 90° (past the 30° smooth angle) keep their own normal at every corner:
    exactly ± one axis, outwards."""
    vertices, faces = _cube(0.5)
    normals = corner_normals(vertices, faces)
    centres = vertices[faces].mean(axis=1)
    outward = np.where(np.abs(centres) > 0.49, np.sign(centres), 0.0)
    assert np.array_equal(normals, np.repeat(outward[:, None, :], 3, axis=1))


def test_the_normal_volume_points_along_a_spheres_radius_on_and_near_it():
    """Each cell the sphere crosses, or within two cells of it, holds the unit normal of the
    surface there: no further from the radius through the cell's centre than the angle a cell's
    diagonal spans from the sphere's centre (4.96°; measured 4.19°); cells further in or out
    hold none."""
    radius, cell = 0.4, 0.02
    vertices, faces = _uv_sphere(radius)
    shape = (48, 48, 48)
    box_min = np.full(3, -cell * 24)
    volume = normal_volume(vertices, faces, corner_normals(vertices, faces), box_min, cell, shape, spread_cells=2)
    centres = box_min + cell * (np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1) + 0.5)
    distance = np.abs(np.linalg.norm(centres, axis=-1) - radius)
    held = np.linalg.norm(volume, axis=-1) > 0
    near = distance < cell * 0.5  # cells whose centre lies within half a cell of the surface
    assert held[near].all()
    assert np.allclose(np.linalg.norm(volume[held], axis=-1), 1.0, atol=1e-5)
    assert _angle_deg(volume[held], centres[held]).max() < math.degrees(cell * math.sqrt(3) / radius)
    assert not held[distance > cell * (2 + math.sqrt(3))].any()  # nothing further than the spread
