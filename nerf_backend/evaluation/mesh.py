"""A trained NeRF's geometry as a mesh: marching cubes over its density inside the scene's
box, vertex colours from the field seen from outside, in Blender's world coordinates.

The default threshold follows the density-to-opacity relation ``α = 1 − exp(−σ δ)`` at the
step δ the model's renderer takes along a ray (a marched model's step; for the NeRF's
continuous sampling, the mesh's voxel size): the surface is where one step is half opaque,
``σ = ln 2 / δ``. Below it the renderer sees mostly through a sample, above it mostly not,
so the mesh's surface is where the images' surfaces are.

Example:
    >>> import torch
    >>> from nerf_backend.core.scene_bounds import SceneBounds
    >>> ball = lambda x: torch.where(x.norm(dim=-1) < 0.5, 100.0, 0.0)
    >>> mesh = extract_mesh(ball, lambda x, d: torch.ones_like(x), SceneBounds((-1,) * 3, (1,) * 3), 48)
    >>> radius = mesh.vertices.norm(dim=-1)
    >>> bool((radius - 0.5).abs().max() < 2 / 47)  # within one voxel of the true sphere
    True
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from skimage.measure import marching_cubes
from torch import Tensor

from ..core.errors import NerfError
from ..core.field_functions import ColourFn, DensityFn
from ..core.files import write_json
from ..core.scene_bounds import SceneBounds
from ..core.world_frame import world_to_nerf_matrix
from ..data.dataset import load_scene_profile
from ..data.run_folder import RunFolder
from ..model_components.ray_bounds import PROTOCOL_BOX, RayBounds
from .inference import load_trained_model


@dataclass
class Mesh:
    vertices: Tensor  # [V, 3] float64
    faces: Tensor  # [F, 3] int64, counter-clockwise seen from outside (Blender's front faces)
    normals: Tensor  # [V, 3] outward unit normals
    colours: Tensor  # [V, 3] in [0, 1]


def default_threshold(voxel_size: float) -> float:
    """The density at which a step of ``voxel_size`` is half opaque: ``ln 2 / δ``.

    Example:
        >>> round(default_threshold(0.02), 3)
        34.657
    """
    return math.log(2.0) / voxel_size


@torch.no_grad()
def sample_density(density_fn: DensityFn, box: SceneBounds, resolution: int, device: torch.device | str = "cpu",
                   chunk: int = 65536) -> tuple[np.ndarray, tuple[float, float, float]]:
    """Density on a grid of ``resolution`` vertices along the box's longest side (cubic
    voxels), ``[Nx, Ny, Nz]``, and the voxel size on each axis."""
    extent = [hi - lo for lo, hi in zip(box.box_min, box.box_max)]
    voxel = max(extent) / (resolution - 1)
    counts = [max(2, round(side / voxel) + 1) for side in extent]
    axes = [torch.linspace(lo, lo + (n - 1) * voxel, n, device=device) for lo, n in zip(box.box_min, counts)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).view(-1, 3)
    density = torch.cat([density_fn(part).float() for part in points.split(chunk)])
    return density.view(*counts).cpu().numpy(), (voxel, voxel, voxel)


@torch.no_grad()
def extract_mesh(density_fn: DensityFn, colour_fn: ColourFn | None, box: SceneBounds, resolution: int,
                 threshold: float | None = None, device: torch.device | str = "cpu",
                 render_step: float | None = None) -> Mesh:
    """Marching cubes at ``threshold`` (default: ``default_threshold`` of ``render_step``, or
    of the voxel size without one) over the density inside ``box``; each vertex coloured by
    ``colour_fn`` looking at it along its inward normal (as a camera outside would); without
    one, no colours (``[0, 3]``: a caller that colours the surface its own way)."""
    volume, spacing = sample_density(density_fn, box, resolution, device)
    level = default_threshold(render_step or spacing[0]) if threshold is None else threshold
    if not volume.min() < level < volume.max():
        raise NerfError(f"mesh: no surface at density {level:g}: the density inside the box ranges "
                        f"{volume.min():g} to {volume.max():g}; give a threshold within that range (mesh --threshold, "
                        "eval --geometry --mesh-threshold)")
    vertices, faces, normals, _ = marching_cubes(volume, level, spacing=spacing)
    vertices = torch.from_numpy(vertices.astype(np.float64)) + torch.tensor(box.box_min, dtype=torch.float64)
    # scikit-image winds faces clockwise seen from the denser side's outside; Blender's front
    # faces are counter-clockwise, so each face is turned over. Its normals already point out.
    faces = torch.from_numpy(faces[:, [0, 2, 1]].astype(np.int64))
    normals = torch.nn.functional.normalize(torch.from_numpy(normals.astype(np.float64)), dim=-1)
    if colour_fn is None:
        return Mesh(vertices, faces, normals, torch.zeros(0, 3))
    colours = torch.cat([colour_fn(v.float().to(device), -n.float().to(device)).float().cpu()
                         for v, n in zip(vertices.split(65536), normals.split(65536))]).clamp(0, 1)
    return Mesh(vertices, faces, normals, colours)


def to_blender_world(mesh: Mesh, world_to_nerf: dict | None) -> Mesh:
    """The mesh back in Blender's world: the inverse of the dataset's ``world_to_nerf`` (its
    4×4 ``matrix``, else ``scale`` and ``translation``); normals follow (inverse transpose)."""
    if world_to_nerf is None:
        return mesh
    matrix = world_to_nerf_matrix(world_to_nerf)
    inverse = torch.linalg.inv(matrix)
    vertices = mesh.vertices @ inverse[:3, :3].T + inverse[:3, 3]
    # Points map by A⁻¹, so normals map by (A⁻¹)⁻ᵀ = Aᵀ: as rows, n @ A.
    normals = torch.nn.functional.normalize(mesh.normals @ matrix[:3, :3], dim=-1)
    return Mesh(vertices, mesh.faces, normals, mesh.colours)


def write_ply(path: Path, mesh: Mesh) -> None:
    """Binary little-endian PLY with per-vertex normals and 8-bit colours (Blender imports
    the colours as a colour attribute)."""
    vertex = np.empty(len(mesh.vertices), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"),
                                                  ("ny", "<f4"), ("nz", "<f4"), ("red", "u1"), ("green", "u1"),
                                                  ("blue", "u1")])
    for axis, name in enumerate("xyz"):
        vertex[name] = mesh.vertices[:, axis].numpy()
        vertex[f"n{name}"] = mesh.normals[:, axis].numpy()
    for axis, name in enumerate(("red", "green", "blue")):
        vertex[name] = np.round(mesh.colours[:, axis].numpy() * 255).astype(np.uint8)
    face = np.empty(len(mesh.faces), dtype=[("count", "u1"), ("indices", "<i4", (3,))])
    face["count"] = 3
    face["indices"] = mesh.faces.numpy()
    header = (f"ply\nformat binary_little_endian 1.0\ncomment written by python -m nerf_backend mesh\n"
              f"element vertex {len(vertex)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"property float nx\nproperty float ny\nproperty float nz\n"
              f"property uchar red\nproperty uchar green\nproperty uchar blue\n"
              f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n")
    partial = path.with_name(path.name + ".partial")
    with open(partial, "wb") as out:
        out.write(header.encode("ascii"))
        out.write(vertex.tobytes())
        out.write(face.tobytes())
    partial.replace(path)


def write_obj(path: Path, mesh: Mesh) -> None:
    """Wavefront OBJ with vertex colours after each position (``v x y z r g b``, read by
    Blender's importer) and normals."""
    lines = ["# written by python -m nerf_backend mesh"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f} {r:.4f} {g:.4f} {b:.4f}"
              for (x, y, z), (r, g, b) in zip(mesh.vertices.tolist(), mesh.colours.tolist())]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.normals.tolist()]
    lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in (mesh.faces + 1).tolist()]
    partial = path.with_name(path.name + ".partial")
    partial.write_text("\n".join(lines) + "\n", encoding="ascii")
    partial.replace(path)


MESH_WRITERS = {".ply": write_ply, ".obj": write_obj}


def run_mesh(run: RunFolder, device: torch.device, resolution: int = 256,
             threshold: float | None = None) -> tuple[Mesh, dict]:
    """The run's latest checkpoint as a mesh in the NeRF frame (the dataset's), and how it was
    extracted: what ``mesh`` writes and ``eval --geometry`` scores."""
    model, ray_bounds, state = load_trained_model(run, device)
    return model_mesh(model, ray_bounds, state["iteration"], device, resolution, threshold)


def model_mesh(model, ray_bounds: RayBounds, iteration: int, device: torch.device, resolution: int = 256,
               threshold: float | None = None, coloured: bool = True) -> tuple[Mesh, dict]:
    """``run_mesh`` of a model already loaded (``load_trained_model``); ``coloured=False``
    leaves the vertices without colours (``export`` bakes a texture instead)."""
    colour_fn = model.colour_at if coloured else None
    if resolution < 8:
        raise NerfError(f"mesh: resolution {resolution}: at least 8 vertices along the box's longest side")
    box = ray_bounds.box if ray_bounds.box is not None else PROTOCOL_BOX
    render_step = getattr(model, "step", None)  # a marched model's step along each ray
    voxel = max(hi - lo for lo, hi in zip(box.box_min, box.box_max)) / (resolution - 1)
    surface = model.surface_function()
    if surface is not None and threshold is None:  # a signed distance: its zero level set
        mesh = extract_mesh(surface, colour_fn, box, resolution, 0.0, device)
        level, rule = 0.0, "the signed distance's zero level set"
    else:
        mesh = extract_mesh(model.density_at, colour_fn, box, resolution, threshold, device, render_step)
        level = threshold if threshold is not None else default_threshold(render_step or voxel)
        rule = ("given" if threshold is not None else
                f"ln 2 / step: the density at which one render step ({render_step or voxel:.5g}) is half opaque")
    return mesh, {
        "iteration": iteration, "vertices": len(mesh.vertices), "faces": len(mesh.faces),
        "resolution": resolution, "voxel_size": voxel, "box": {"min": list(box.box_min), "max": list(box.box_max)},
        "threshold": level, "threshold_rule": rule,
    }


def mesh_run(run: RunFolder, out: Path, device: torch.device, resolution: int = 256,
             threshold: float | None = None, overwrite: bool = False) -> dict:
    """The run's latest checkpoint as a mesh file (``.ply`` or ``.obj``) in Blender's world
    coordinates, and ``OUT.json`` beside it: what was extracted, and how."""
    if out.suffix.lower() not in MESH_WRITERS:
        raise NerfError(f"{out}: a mesh is written as .ply or .obj")
    record_path = out.with_name(out.name + ".json")
    if (out.exists() or record_path.exists()) and not overwrite:
        raise NerfError(f"{out}: exists; pass --overwrite to replace it")
    mesh, how = run_mesh(run, device, resolution, threshold)
    profile = load_scene_profile(run.read_config()["dataset"])
    mesh = to_blender_world(mesh, profile.get("world_to_nerf") if profile else None)
    out.parent.mkdir(parents=True, exist_ok=True)
    MESH_WRITERS[out.suffix.lower()](out, mesh)
    record = {"mesh": str(out), **how, "frame": "Blender world (the inverse of the dataset's world_to_nerf)"}
    write_json(record_path, record)
    return record
