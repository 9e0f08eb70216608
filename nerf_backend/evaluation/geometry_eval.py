"""``eval --geometry``: a trained NeRF's surface measured against the scene's true one.

The truth is ``scene_geometry.ply``, which ``datasets_gen`` writes beside the views: every
renderable triangle (after modifiers and instancing) in the NeRF frame. The NeRF's surface is
the ``mesh`` command's, in the same frame. Both are sampled uniformly by area (fixed seed) and
scored as ``metrics/geometry.py`` says: accuracy, completeness, Chamfer distance (their mean),
precision / recall / F-score at ``τ`` = 1 % of the scene's bounding-sphere radius, and normal
consistency. The truth holds surfaces no camera sees (insides, undersides on a floor), which
the NeRF cannot learn: they count against its recall and completeness, the same for every run.

``RUN/geometry.json`` holds the scores and how they were made; ``RUN/geometry.png`` shows the
NeRF's surface coloured by its distance to the truth, over the truth in grey.

Example (a ball of radius 0.5 against a truth sphere of the same radius):
    >>> import torch
    >>> from nerf_backend.core.scene_bounds import SceneBounds
    >>> from .mesh import extract_mesh
    >>> box = SceneBounds((-1,) * 3, (1,) * 3)
    >>> ball = lambda r: (lambda x: torch.where(x.norm(dim=-1) < r, 100.0, 0.0))
    >>> mesh = extract_mesh(ball(0.5), lambda x, d: torch.ones_like(x), box, 64)
    >>> truth = extract_mesh(ball(0.5), lambda x, d: torch.ones_like(x), box, 96)
    >>> scores, _ = compare_surfaces(mesh.vertices.numpy(), mesh.faces.numpy(), truth.vertices.numpy(),
    ...                              truth.faces.numpy(), tau=0.05, samples=5000)
    >>> scores["f_score"] > 0.99
    True
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..core.errors import NerfError
from ..core.files import write_json
from ..core.ply import read_ply
from ..data.dataset import load_scene_profile
from ..data.run_folder import RunFolder
from ..metrics.geometry import nearest_points, sample_surface, surface_area, surface_distances
from .mesh import run_mesh
from .report_plots import plot_surface_error

GEOMETRY_NAME = "geometry.json"
GEOMETRY_PICTURE = "geometry.png"
TAU_FRACTION = 0.01
TAU_RULE = "1 % of the scene's bounding-sphere radius (scene_profile.json bounding_sphere.radius)"
# Each surface is sampled about τ / 4 apart, so that the samples' own spacing hardly moves a
# point across τ; it still adds about an eighth of τ to a mean distance (a sample's nearest on
# the same surface). Within these limits:
SAMPLE_SPACING = 0.25
MIN_SAMPLES, MAX_SAMPLES = 10_000, 2_000_000
# Of which this many a surface are matched to the other's (a fraction's standard error < 0.0012).
QUERIES = 200_000
DEFAULT_RESOLUTION = 256  # the mesh command's
SEED = 0
DRAWN_POINTS = 30_000  # of each surface, in the picture


# The scores for people: (key, label, decimals); distances are in the dataset's units.
GEOMETRY_SCORES = (
    ("chamfer", "Chamfer distance (mean of the two below)", 4), ("accuracy", "accuracy: NeRF to truth, mean", 4),
    ("completeness", "completeness: truth to NeRF, mean", 4), ("precision", "precision at τ", 3),
    ("recall", "recall at τ", 3), ("f_score", "F-score at τ", 3), ("normal_consistency", "normal consistency", 3),
)


@dataclass
class Truth:
    """A dataset's true surface and the distance its scores are counted at."""

    path: Path
    vertices: np.ndarray
    faces: np.ndarray
    tau: float
    record: dict  # the profile's `geometry` entry


def truth_file(dataset: Path | str) -> Path | None:
    """The true surface the dataset's profile names (``scene_geometry.ply``), or None."""
    record = (load_scene_profile(dataset) or {}).get("geometry")
    return Path(dataset) / record["file"] if isinstance(record, dict) and "file" in record else None


def scene_tau(dataset: Path | str) -> float:
    """The distance the F-score counts at: TAU_FRACTION of the profile's bounding-sphere radius."""
    profile = load_scene_profile(dataset) or {}
    radius = (profile.get("bounding_sphere") or {}).get("radius")
    if not isinstance(radius, (int, float)) or not radius > 0:
        raise NerfError(f"{Path(dataset) / 'scene_profile.json'}: bounding_sphere.radius must be a positive number, "
                        f"got {radius!r}")
    return TAU_FRACTION * float(radius)


def load_truth(dataset: Path | str) -> Truth:
    """The dataset's true surface; a NerfError naming the dataset's file when it has none."""
    profile = load_scene_profile(dataset)
    path = truth_file(dataset)
    if profile is None or path is None:
        why = ("no scene_profile.json: not a datasets_gen dataset" if profile is None
               else profile.get("geometry_reason") or "the dataset was made before datasets_gen wrote scene_geometry.ply")
        raise NerfError(f"{Path(dataset) / 'scene_profile.json'}: the dataset has no scene geometry to measure "
                        f"against ({why}); regenerate it with python -m datasets_gen (in a Blender with numpy) to "
                        "write scene_geometry.ply")
    tau = scene_tau(dataset)
    vertices, faces = read_ply(path)
    return Truth(path, vertices, faces, tau, profile["geometry"])


def sample_count(area: float, tau: float) -> int:
    """Points enough to lie about ``τ / 4`` apart on a surface of ``area`` (within the limits).

    Example:
        >>> sample_count(1.0, 0.04), sample_count(1.0, 0.001) == MAX_SAMPLES
        (10000, True)
    """
    return int(min(MAX_SAMPLES, max(MIN_SAMPLES, math.ceil(area / (SAMPLE_SPACING * tau) ** 2))))


def _sample(vertices: np.ndarray, faces: np.ndarray, tau: float, samples: int | None, rng: np.random.Generator,
            what: str) -> tuple[np.ndarray, np.ndarray]:
    area = surface_area(vertices, faces) if len(faces) else 0.0
    if not area > 0:
        raise NerfError(f"geometry: {what} has no area to measure")
    return sample_surface(vertices, faces, samples or sample_count(area, tau), rng)


def compare_surfaces(vertices: np.ndarray, faces: np.ndarray, true_vertices: np.ndarray, true_faces: np.ndarray,
                     tau: float, samples: int | None = None,
                     seed: int = SEED) -> tuple[dict, tuple[np.ndarray, np.ndarray]]:
    """The scores of a reconstructed mesh against the true one, and the sampled points of both
    (reconstruction, truth). Each surface gets ``samples`` points, by default ``sample_count``'s."""
    rng = np.random.default_rng(seed)
    points, normals = _sample(vertices, faces, tau, samples, rng, "the NeRF's mesh")
    true_points, true_normals = _sample(true_vertices, true_faces, tau, samples, rng, "the true surface")
    scores = surface_distances(points, normals, true_points, true_normals, tau, QUERIES)
    return scores, (points, true_points)


def score_geometry(run: RunFolder, device: torch.device, resolution: int = DEFAULT_RESOLUTION,
                   threshold: float | None = None, samples: int | None = None) -> dict:
    """Mesh the run's latest checkpoint, score it against its dataset's true surface, and
    write ``RUN/geometry.json`` and ``RUN/geometry.png``."""
    truth = load_truth(run.read_config()["dataset"])
    mesh, how = run_mesh(run, device, resolution, threshold)
    scores, (points, true_points) = compare_surfaces(mesh.vertices.numpy(), mesh.faces.numpy(), truth.vertices,
                                                     truth.faces, truth.tau, samples)
    picture = run.path / GEOMETRY_PICTURE
    drawn = points[:DRAWN_POINTS]  # the samples are in random order: any prefix is uniform
    plot_surface_error(picture, drawn, nearest_points(true_points, drawn)[0], true_points[:DRAWN_POINTS], truth.tau)
    record = {
        **scores,
        "tau_rule": TAU_RULE,
        "units": "NeRF-frame units (the dataset's, after world_to_nerf)",
        "samples": {"nerf": len(points), "truth": len(true_points)}, "seed": SEED,
        "sampling": f"uniform by area on each surface, about τ / {1 / SAMPLE_SPACING:g} apart (at most {MAX_SAMPLES:,} "
                    f"points); {QUERIES:,} of a surface's points matched to the nearest sampled point of the other",
        "truth": {"file": str(truth.path), "triangles": len(truth.faces), "left_out": truth.record.get("left_out", []),
                  "beyond_mesh": truth.record.get("beyond_mesh", [])},
        "mesh": how,
        "picture": str(picture),
    }
    write_json(run.path / GEOMETRY_NAME, record)
    return record


def geometry_line(record: dict) -> str:
    """One line for people: Chamfer, F-score at τ, normal consistency."""
    return (f"geometry: Chamfer {record['chamfer']:.4f}, F-score {record['f_score']:.3f} at τ = {record['tau']:.4f}, "
            f"normal consistency {record['normal_consistency']:.3f} (mesh at resolution {record['mesh']['resolution']}, "
            f"density {record['mesh']['threshold']:.4g})")
