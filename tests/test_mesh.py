"""Geometry out of a NeRF: marching cubes over analytic densities against their closed-form
surfaces, the threshold rule, the files, a trained run meshed through the CLI, and the
geometric scores (Chamfer, F-score, normal consistency) against closed forms."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from conftest import run_python

from nerf_backend.core.errors import NerfError
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.evaluation.mesh import default_threshold, extract_mesh, to_blender_world, write_obj, write_ply
from nerf_backend.metrics.geometry import fibonacci_sphere, sample_surface, surface_distances

BOX = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))


def _ball(radius: float, density: float = 200.0):
    return lambda x: torch.where(x.norm(dim=-1) < radius, density, 0.0)


def _colour_from_direction(x, d):
    """Encodes the viewing direction: a test of which way each vertex is looked at."""
    return (d + 1.0) / 2.0


def test_the_threshold_is_where_one_step_is_half_opaque():
    step = 0.013
    assert 1.0 - math.exp(-default_threshold(step) * step) == pytest.approx(0.5)


@pytest.mark.parametrize("resolution", [32, 64])
def test_a_ball_meshes_onto_its_sphere_within_a_voxel(resolution):
    mesh = extract_mesh(_ball(0.6), _colour_from_direction, BOX, resolution)
    voxel = 2.0 / (resolution - 1)
    radius = mesh.vertices.norm(dim=-1)
    assert (radius - 0.6).abs().max() <= voxel  # a step density: the surface lies within one voxel
    # Outward normals (from a step density's gradient: coarse, but never inward), faces wound
    # counter-clockwise seen from outside (Blender's front faces).
    cosine = torch.nn.functional.cosine_similarity(mesh.normals, mesh.vertices, dim=-1)
    assert (cosine > 0).all() and cosine.median() > 0.85  # measured: median 0.92 at 32 and 64
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    assert ((torch.cross(b - a, c - a, dim=-1) * (a + b + c)).sum(dim=-1) > 0).all()
    # Each vertex is coloured as seen from outside: looking along its inward normal.
    assert torch.allclose(mesh.colours, ((-mesh.normals).float() + 1) / 2, atol=1e-5)


def test_a_smooth_density_meshes_at_the_threshold_radius():
    """σ(r) = 100·(1 − r): the surface at the default threshold is the sphere σ = ln 2 / δ."""
    resolution = 65
    voxel = 2.0 / (resolution - 1)
    mesh = extract_mesh(lambda x: 100.0 * (1.0 - x.norm(dim=-1)).clamp_min(0), _colour_from_direction, BOX, resolution)
    expected = 1.0 - default_threshold(voxel) / 100.0
    assert (mesh.vertices.norm(dim=-1) - expected).abs().max() < 0.01


def test_a_box_density_meshes_onto_its_faces():
    half = torch.tensor([0.5, 0.3, 0.2])
    mesh = extract_mesh(lambda x: ((x.abs() < half).all(dim=-1)).float() * 300.0, _colour_from_direction, BOX, 64)
    low, high = mesh.vertices.min(dim=0).values, mesh.vertices.max(dim=0).values
    assert torch.allclose(high, half.double(), atol=2.0 / 63) and torch.allclose(low, -half.double(), atol=2.0 / 63)


def test_no_surface_at_the_threshold_is_named():
    with pytest.raises(NerfError, match="no surface at density"):
        extract_mesh(lambda x: torch.zeros(x.shape[0]), _colour_from_direction, BOX, 16)


def test_blender_world_is_the_inverse_of_world_to_nerf():
    mesh = extract_mesh(_ball(0.5), _colour_from_direction, BOX, 24)
    world_to_nerf = {"matrix": [[0.5, 0, 0, 0.1], [0, 0.5, 0, -0.2], [0, 0, 0.5, 0.3], [0, 0, 0, 1]]}
    back = to_blender_world(mesh, world_to_nerf)
    assert torch.allclose(back.vertices, (mesh.vertices - torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)) / 0.5)
    assert torch.allclose(back.normals, mesh.normals)  # a uniform scale keeps directions


def test_ply_and_obj_files_hold_the_mesh(tmp_path):
    mesh = extract_mesh(_ball(0.5), _colour_from_direction, BOX, 20)
    write_ply(tmp_path / "m.ply", mesh)
    write_obj(tmp_path / "m.obj", mesh)
    data = (tmp_path / "m.ply").read_bytes()
    header, body = data.split(b"end_header\n", 1)
    assert f"element vertex {len(mesh.vertices)}".encode() in header and f"element face {len(mesh.faces)}".encode() in header
    assert len(body) == len(mesh.vertices) * (6 * 4 + 3) + len(mesh.faces) * (1 + 3 * 4)
    lines = (tmp_path / "m.obj").read_text().splitlines()
    assert sum(line.startswith("v ") for line in lines) == len(mesh.vertices)
    assert sum(line.startswith("f ") for line in lines) == len(mesh.faces)
    assert not list(tmp_path.glob("*.partial"))


def test_a_trained_run_meshes_through_the_cli(trained_run, tmp_path):
    out = tmp_path / "demo.ply"
    # The preview NeRF after 250-400 steps is soft (its densest point: 17.5 a unit at 400), below the
    # default rule's ln 2 / voxel = 17.4 at this resolution: a threshold is given.
    result = run_python("-m", "nerf_backend", "mesh", str(trained_run), "--resolution", "48", "--threshold", "5",
                        "--out", str(out))
    record = json.loads((tmp_path / "demo.ply.json").read_text())
    assert record["vertices"] > 100 and record["faces"] > 100 and "mesh" in result.stdout
    assert record["threshold"] == 5.0 and record["threshold_rule"] == "given"
    again = run_python("-m", "nerf_backend", "mesh", str(trained_run), "--out", str(out), check=False)
    assert again.returncode == 2 and "exists; pass --overwrite" in again.stderr
    header = out.read_bytes().split(b"end_header\n", 1)[0].decode()
    count = int(header.split("element vertex ")[1].split("\n")[0])
    vertices = np.frombuffer(out.read_bytes().split(b"end_header\n", 1)[1][: count * 27], dtype=np.dtype(
        [("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)]))
    # The demo's objects sit inside its box: the mesh does too.
    box = record["box"]
    assert (vertices["p"] >= np.array(box["min"]) - 1e-4).all() and (vertices["p"] <= np.array(box["max"]) + 1e-4).all()


def test_mesh_writes_refuse_other_suffixes(trained_run, tmp_path):
    result = run_python("-m", "nerf_backend", "mesh", str(trained_run), "--out", str(tmp_path / "m.stl"), check=False)
    assert result.returncode == 2 and "a mesh is written as .ply or .obj" in result.stderr



def test_geometry_scores_of_two_concentric_spheres_match_the_closed_form():
    """Radii 1 and 1.05: every point's nearest neighbour on the other sphere is 0.05 away
    along its radius (plus the sampling's spacing), normals are parallel."""
    inner, outer = fibonacci_sphere(20000), fibonacci_sphere(20000) * 1.05
    spacing = math.sqrt(4 * math.pi * 1.05**2 / 20000)  # mean distance between samples
    scores = surface_distances(inner, inner, outer, outer / 1.05, tau=0.06)
    for key in ("accuracy", "completeness", "chamfer"):
        assert 0.05 - 1e-9 <= scores[key] <= math.hypot(0.05, spacing / 2), key
    assert scores["precision"] == scores["recall"] == scores["f_score"] == 1.0
    assert scores["normal_consistency"] > 0.999
    below = surface_distances(inner, inner, outer, outer / 1.05, tau=0.049)
    assert below["precision"] == below["recall"] == below["f_score"] == 0.0


def test_geometry_scores_of_a_mesh_against_itself_and_a_missing_half():
    # σ = 200·(0.6 − r) meshed at σ = 20: the sphere of radius 0.5.
    mesh = extract_mesh(lambda x: 200.0 * (0.6 - x.norm(dim=-1)).clamp_min(0), _colour_from_direction, BOX, 48,
                        threshold=20.0)
    rng = np.random.default_rng(0)
    points, normals = sample_surface(mesh.vertices.numpy(), mesh.faces.numpy(), 20000, rng)
    # Sampled normals follow the faces' winding: outward.
    assert (np.einsum("ij,ij->i", points, normals) > 0).all()
    truth = fibonacci_sphere(20000) * 0.5
    scores = surface_distances(points, normals, truth, truth / 0.5, tau=0.02)  # above the spacing
    # Both sides are samples: a nearest neighbour is up to half the samples' spacing away even
    # on the same surface; the facets' own error (sagitta ~ 0.0005) is smaller.
    spacing = math.sqrt(4 * math.pi * 0.5**2 / 20000)
    assert scores["chamfer"] < 0.5 * spacing + 0.001
    assert scores["f_score"] > 0.95 and scores["normal_consistency"] > 0.99
    upper = points[:, 2] > 0  # half the surface missing: precision stays, recall halves
    half = surface_distances(points[upper], normals[upper], truth, truth / 0.5, tau=0.02)
    assert half["precision"] > 0.95 and 0.45 < half["recall"] < 0.6
