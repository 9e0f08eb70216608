"""A trained run as a textured asset: its surface (``mesh``'s: a surface run's zero level set,
else the density's marching-cubes surface), decimated to a triangle budget, unwrapped into a UV
atlas, the field's colour baked into the atlas's texture from the training views, written as
glTF binary in Blender's world frame, with ``ASSET.glb.json`` beside it saying what was made
and what each stage cost."""

from __future__ import annotations

import time
from pathlib import Path

import torch

from nerf_contract.run_layout import ASSET_COMPLETE, ASSET_RECORD_SUFFIX, ASSET_STAGES, ASSET_STAGES_DONE

from ..core.errors import NerfError
from ..core.files import write_json
from ..core.progress import Progress
from ..data.dataset import load_scene_profile, load_split_poses
from ..data.run_folder import RunFolder
from ..evaluation.inference import load_trained_model
from ..evaluation.mesh import Mesh, model_mesh, to_blender_world
from ..models.base import Model, final_output
from .bake import VIEWS_PER_TEXEL, bake_texels, colour_seen_near
from .decimate import decimate, vertex_normals
from .gltf import write_glb
from .texture_space import dilate, rasterise_uv
from .uv_atlas import GUTTER_TEXELS, unwrap

DEFAULT_TRIANGLES = 50_000
DEFAULT_TEXTURE_SIZE = 2048
MIN_TEXTURE_SIZE, MAX_TEXTURE_SIZE = 64, 8192
ASSET_SUFFIX = ".glb"
# How far either side of a texel's point the bake renders each camera's ray, in cells of the
# surface's grid: past the field's spread about its surface and what decimation moves it.
# Measured on A.blend at 48×48 (surface, 600 steps; NeRF 33.96 dB; the surface's cells a third
# of the field's), the asset by Cycles: 4 cells 31.53 dB, 8: 32.25, 12: 32.45, 16: 32.51, 24:
# 32.56; the field's colour at the point, as before, 30.95.
REACH_CELLS = 16


STAGES = ("surface", "decimate", "unwrap", "rasterise", "bake", "write")


def record_path(asset: Path) -> Path:
    """``ASSET.glb.json``: what ``export`` made, beside the asset (and, while it works, how far
    it got: nerf_contract.run_layout)."""
    return asset.with_name(asset.name + ASSET_RECORD_SUFFIX)


def export_run(run: RunFolder, out: Path, device: torch.device, triangles: int = DEFAULT_TRIANGLES,
               texture_size: int = DEFAULT_TEXTURE_SIZE, resolution: int = 256, threshold: float | None = None,
               overwrite: bool = False, progress: bool = True) -> dict:
    """Write the run's asset to ``out`` (``.glb``) and its record beside it; returns the record.
    ``resolution`` and ``threshold``: the surface's, as ``mesh`` takes them."""
    if out.suffix.lower() != ASSET_SUFFIX:
        raise NerfError(f"{out}: an asset is written as glTF binary, {ASSET_SUFFIX}")
    if not MIN_TEXTURE_SIZE <= texture_size <= MAX_TEXTURE_SIZE:
        raise NerfError(f"a texture size of {texture_size}: between {MIN_TEXTURE_SIZE} and {MAX_TEXTURE_SIZE} texels")
    if (out.exists() or record_path(out).exists()) and not overwrite:
        raise NerfError(f"{out}: exists; pass --overwrite to replace it")
    dataset = run.read_config()["dataset"]
    poses = load_split_poses(dataset, "train")  # read first: a dataset moved away fails before the work
    seconds: dict[str, float] = {}
    bar = Progress(total=len(STAGES), description="export", unit="stage", enabled=progress)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json(record_path(out), {"asset": str(out), ASSET_STAGES_DONE: 0, ASSET_STAGES: len(STAGES),
                                  ASSET_COMPLETE: False})

    def stage(name: str, start: float) -> float:
        seconds[name] = round(time.perf_counter() - start, 3)
        bar.update(1)
        bar.set_postfix(done=name)
        if name != STAGES[-1]:
            write_json(record_path(out), {"asset": str(out), ASSET_STAGES_DONE: len(seconds), ASSET_STAGES: len(STAGES),
                                          ASSET_COMPLETE: False, "seconds": seconds})
        return time.perf_counter()

    now = time.perf_counter()
    model, ray_bounds, state = load_trained_model(run, device)
    mesh, how = model_mesh(model, ray_bounds, state["iteration"], device, resolution, threshold, coloured=False)
    now = stage("surface", now)
    vertices, faces = decimate(mesh.vertices, mesh.faces, triangles)
    normals = vertex_normals(vertices, faces)
    now = stage("decimate", now)
    atlas = unwrap(vertices, faces, texture_size)
    atlas_vertices, atlas_normals = vertices[atlas.source_vertex], normals[atlas.source_vertex]
    now = stage("unwrap", now)
    cover = rasterise_uv(atlas.uv, atlas.faces, texture_size)
    now = stage("rasterise", now)
    seen = colour_seen_near(_render_fn(model), REACH_CELLS * how["voxel_size"])
    baked = bake_texels(seen, atlas_vertices, atlas_normals, atlas.faces, cover, poses[:, :3, 3],
                        device=device)
    texture = dilate(baked.colours, baked.filled, GUTTER_TEXELS)
    now = stage("bake", now)
    profile = load_scene_profile(dataset)
    world = to_blender_world(Mesh(atlas_vertices, atlas.faces, atlas_normals, mesh.colours),
                             profile.get("world_to_nerf") if profile else None)
    size = write_glb(out, world.vertices, world.normals, atlas.uv, atlas.faces, texture, out.stem)
    stage("write", now)
    bar.close()
    record = {
        "asset": str(out), "bytes": size, "triangles": len(atlas.faces), "vertices": len(atlas_vertices),
        "triangle_budget": triangles, "surface_triangles": len(mesh.faces), "texture_size": texture_size,
        "texels_covered": round(float(baked.filled.float().mean()), 4),
        "bake": (f"the colour the NeRF renders at each texel's surface point (within {REACH_CELLS} surface cells "
                 f"either side of it) along the rays of the {VIEWS_PER_TEXEL} training views facing it most squarely "
                 "that see it, cosine-weighted: view-dependent colour bakes to that average; unlit material "
                 "(KHR_materials_unlit), the lighting is in the texture"),
        "frame": "Blender world (the inverse of the dataset's world_to_nerf), written glTF Y-up",
        "surface": how, "seconds": seconds, ASSET_STAGES_DONE: len(STAGES), ASSET_STAGES: len(STAGES),
        ASSET_COMPLETE: True,
    }
    write_json(record_path(out), record)
    return record


def _render_fn(model: Model):
    """The model's render of stretches of rays over no background (bake.RenderFn), its own
    ``render_chunk`` rays at a time (what bounds its memory)."""
    chunk = model.render_chunk  # read once: the property looks up the compiled march

    def render(origins, directions, t_near, t_far):
        parts = []
        for start in range(0, len(origins), chunk):
            rays = slice(start, start + chunk)
            output = final_output(model(origins[rays], directions[rays], t_near[rays], t_far[rays], background=0.0))
            parts.append((output.rgb, output.opacity, output.depth))
        return tuple(torch.cat(part) for part in zip(*parts))
    return render
