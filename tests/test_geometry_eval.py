"""The NeRF's geometry against the scene's true surface: the truth's PLY file written by
datasets_gen and read by the backend, the scores of an analytic ball against a true sphere
(F-score 1 at the same radius, 0 three τ away), ``eval --geometry`` on a trained run, and a
dataset without a true surface refused in one line."""

from __future__ import annotations

import doctest
import json
import math
import shutil

import numpy as np
import pytest
import torch
from conftest import run_python
from PIL import Image

from datasets_gen.io import surface_mesh
from datasets_gen.io.surface_mesh import ply_bytes, weld, write_ply_atomic
from datasets_gen.io.surface_mesh import read_ply as datasets_gen_read_ply
from nerf_backend.bench.tables import markdown_table
from nerf_backend.core.errors import NerfError
from nerf_backend.core.ply import read_face_materials, read_ply
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.evaluation.geometry_eval import TAU_FRACTION, compare_surfaces
from nerf_backend.evaluation.mesh import extract_mesh


def uv_sphere(radius: float, segments: int = 160, rings: int = 80) -> np.ndarray:
    """Triangles [T, 3, 3] of a latitude-longitude sphere (the poles' slivers have no area)."""
    theta = np.linspace(0.0, math.pi, rings + 1)[:, None]
    phi = np.linspace(0.0, 2.0 * math.pi, segments + 1)[None, :]
    grid = radius * np.stack(np.broadcast_arrays(np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                                                 np.cos(theta)), axis=-1)
    a, b, c, d = grid[:-1, :-1], grid[:-1, 1:], grid[1:, 1:], grid[1:, :-1]
    return np.concatenate([np.stack([a, c, b], -2).reshape(-1, 3, 3), np.stack([a, d, c], -2).reshape(-1, 3, 3)])


def _corner_sets(triangles: np.ndarray) -> list:
    return sorted(tuple(sorted(map(tuple, triangle))) for triangle in triangles.tolist())


def _signed_volume(triangles: np.ndarray) -> float:
    """Positive for a closed surface wound counter-clockwise seen from outside."""
    return float(np.linalg.det(triangles).sum() / 6.0)


def test_the_truths_ply_round_trips(tmp_path):
    triangles = uv_sphere(0.7, 24, 12)
    materials = np.arange(len(triangles)) % 5  # each face's material goes with it through the sort
    vertices, faces, welded_materials = weld(triangles, materials)
    assert len(vertices) < len(triangles)  # shared corners are one vertex
    write_ply_atomic(str(tmp_path / "scene_geometry.ply"), vertices, faces, welded_materials)
    read_vertices, read_faces = read_ply(tmp_path / "scene_geometry.ply")
    assert read_faces.tolist() == faces.tolist()
    assert read_face_materials(tmp_path / "scene_geometry.ply").tolist() == welded_materials.tolist()
    by_corners = {tuple(sorted(map(tuple, t.astype(np.float32).tolist()))): m for t, m in zip(triangles, materials)}
    assert all(by_corners[tuple(sorted(map(tuple, read_vertices[f].astype(np.float32).tolist())))] == m
               for f, m in zip(read_faces, welded_materials))
    assert datasets_gen_read_ply(str(tmp_path / "scene_geometry.ply"))[1].tolist() == faces.tolist()
    # The same triangles, wound the same way (a canonical order: listed backwards, the same file).
    assert _corner_sets(read_vertices[read_faces]) == _corner_sets(triangles.astype(np.float32).astype(float))
    volume = _signed_volume(triangles)
    assert volume > 0 and _signed_volume(read_vertices[read_faces]) == pytest.approx(volume, rel=1e-5)
    assert ply_bytes(*weld(triangles[::-1], materials[::-1])) == (tmp_path / "scene_geometry.ply").read_bytes()
    write_ply_atomic(str(tmp_path / "without.ply"), vertices, faces)  # a file from before the materials
    assert read_face_materials(tmp_path / "without.ply") is None
    assert not list(tmp_path.glob(".*tmp"))


def test_the_surface_mesh_examples_run():
    assert doctest.testmod(surface_mesh).failed == 0


def test_ply_polygons_become_fans_and_other_files_are_named(tmp_path):
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
              "property float z\nproperty uchar red\nelement face 1\nproperty list uchar uint vertex_indices\n"
              "end_header\n").encode()
    vertex = np.zeros(4, dtype=[("p", "<f4", 3), ("red", "u1")])
    vertex["p"] = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    quad = np.array([4], "u1").tobytes() + np.array([0, 1, 2, 3], "<u4").tobytes()
    (tmp_path / "quad.ply").write_bytes(header + vertex.tobytes() + quad)
    vertices, faces = read_ply(tmp_path / "quad.ply")
    assert vertices.tolist() == vertex["p"].tolist() and faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    (tmp_path / "mesh.stl").write_bytes(b"solid nothing\n")
    with pytest.raises(NerfError, match=r"mesh\.stl: not a PLY file"):
        read_ply(tmp_path / "mesh.stl")
    truncated = ply_bytes(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]]))[:-4]
    (tmp_path / "short.ply").write_bytes(truncated)
    with pytest.raises(NerfError, match=r"short\.ply"):
        read_ply(tmp_path / "short.ply")


# σ = 200·(0.6 − r) meshed at σ = 20: the sphere of radius 0.5, to the facets' sagitta.
RADIUS, BOUNDING_RADIUS = 0.5, 1.5
TAU = TAU_FRACTION * BOUNDING_RADIUS


@pytest.fixture(scope="module")
def ball_mesh():
    box = SceneBounds((-1.0,) * 3, (1.0,) * 3)
    density = lambda x: 200.0 * (0.6 - x.norm(dim=-1)).clamp_min(0)  # noqa: E731
    mesh = extract_mesh(density, lambda x, d: torch.ones_like(x), box, 64, threshold=20.0)
    return mesh.vertices.numpy(), mesh.faces.numpy()


@pytest.mark.parametrize("true_radius, f_score", [(RADIUS, 1.0), (RADIUS + 3 * TAU, 0.0)])
def test_a_ball_against_a_true_sphere(ball_mesh, tmp_path, true_radius, f_score):
    """Same radius: every point within τ both ways, normals parallel. Three τ larger: none
    within τ, and the Chamfer distance is the radii's difference."""
    write_ply_atomic(str(tmp_path / "truth.ply"), *weld(uv_sphere(true_radius))[:2])
    scores, (points, true_points) = compare_surfaces(*ball_mesh, *read_ply(tmp_path / "truth.ply"), tau=TAU,
                                                     samples=50_000)
    assert len(points) == len(true_points) == 50_000
    assert scores["f_score"] == pytest.approx(f_score, abs=0.01)
    # Nearest sampled neighbours are up to about half the samples' spacing off the radial gap.
    spacing = math.sqrt(4 * math.pi * true_radius**2 / 50_000)
    gap = abs(true_radius - RADIUS)
    assert gap - 0.001 <= scores["chamfer"] <= gap + 0.5 * spacing + 0.001
    assert scores["normal_consistency"] > 0.99


def test_bench_table_has_geometry_columns_only_with_a_truth():
    variant = {"name": "fast", "time_to_psnr_s": {"20": 3.0, "25": None, "30": None},
               "render_seconds_per_image": 0.1, "peak_memory_mb": 300.0, "model_size_mb": 2.0,
               "final": {"iterations": 10, "psnr": 21.0, "ssim": 0.8}}
    report = {"budget": {"iterations": 10}, "seed": 0, "machine": {"torch": "2", "threads": 2}, "variants": [variant]}
    assert "Chamfer" not in markdown_table(report)
    collapsed = {**variant, "name": "slim", "final": {**variant["final"], "chamfer": None, "f_score": None,
                                                      "geometry_unavailable": "mesh: no surface at density 30"}}
    variant["final"].update(chamfer=0.0123, f_score=0.456)
    report.update(variants=[variant, collapsed], geometry={"truth": "D/scene_geometry.ply", "mesh_resolution": 128,
                                                           "tau": 0.0123, "tau_rule": "1 % of r"})
    table = markdown_table(report)
    assert "| Chamfer | F-score at τ |" in table and "| 0.0123 | 0.456 |" in table and "| — | — |" in table
    assert "slim: no geometry: mesh: no surface at density 30" in table


def test_eval_geometry_scores_a_trained_run(trained_run, tiny_demo_dataset):
    # The preview NeRF after 250 steps is soft: the mesh command's test threshold (5) is given.
    result = run_python("-m", "nerf_backend", "eval", str(trained_run), "--geometry", "--mesh-resolution", "48",
                        "--mesh-threshold", "5", "--no-progress")
    record = json.loads((trained_run / "geometry.json").read_text())
    profile = json.loads((tiny_demo_dataset / "scene_profile.json").read_text())
    assert record["tau"] == pytest.approx(0.01 * profile["bounding_sphere"]["radius"])
    assert record["truth"]["triangles"] == profile["geometry"]["triangles"]
    assert record["mesh"]["resolution"] == 48 and record["mesh"]["threshold"] == 5.0
    assert 0.0 < record["chamfer"] < 0.2 * profile["bounding_sphere"]["radius"]
    assert 0.0 <= record["f_score"] <= 1.0 and 0.0 < record["normal_consistency"] <= 1.0
    assert "Chamfer" in result.stdout and "F-score" in result.stdout and "mean PSNR" in result.stdout
    with Image.open(trained_run / "geometry.png") as picture:
        assert picture.size[0] > 800


def test_eval_geometry_without_a_true_surface_is_one_line(trained_run, tiny_demo_dataset, tmp_path):
    dataset, run = tmp_path / "dataset", tmp_path / "run"
    dataset.mkdir()
    profile = json.loads((tiny_demo_dataset / "scene_profile.json").read_text())
    del profile["geometry"]  # as datasets_gen wrote it before scene_geometry.ply
    (dataset / "scene_profile.json").write_text(json.dumps(profile))
    shutil.copytree(trained_run, run, ignore=shutil.ignore_patterns("renders", "report", "*.png"))
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "dataset": str(dataset)}))
    result = run_python("-m", "nerf_backend", "eval", str(run), "--geometry", check=False)
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert str(dataset / "scene_profile.json") in result.stderr and "python -m datasets_gen" in result.stderr
