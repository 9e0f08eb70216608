"""The baked asset (``export``): texture space against closed forms, a bake of analytic colour
fields through the real decimator, unwrapper and glTF writer read back texel by texel, and a
trained surface run exported through the CLI."""

from __future__ import annotations

import json
import math

import fast_simplification
import imageio.v3 as iio
import numpy as np
import pygltflib
import pytest
import torch
from conftest import run_python
from skimage.measure import marching_cubes

from nerf_backend.asset.bake import bake_texels, colour_seen_near
from nerf_backend.asset.decimate import decimate, vertex_normals
from nerf_backend.asset.gltf import CLAMP_TO_EDGE, UNLIT, write_glb
from nerf_backend.asset.texture_space import dilate, rasterise_uv
from nerf_backend.asset.uv_atlas import GUTTER_TEXELS, unwrap
from nerf_backend.core.errors import NerfError
from nerf_backend.metrics.geometry import fibonacci_sphere

RADIUS = 0.7


def _sphere_mesh(cells: int = 48) -> tuple[torch.Tensor, torch.Tensor]:
    axis = torch.linspace(-1, 1, cells, dtype=torch.float64)
    inside = RADIUS - torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij")).norm(dim=0)  # positive inside
    vertices, faces, _, _ = marching_cubes(inside.numpy(), 0.0, spacing=(2 / (cells - 1),) * 3)
    # Outward, counter-clockwise faces (as extract_mesh turns scikit-image's over).
    return torch.from_numpy(vertices.copy()) - 1.0, torch.from_numpy(faces[:, [0, 2, 1]].copy()).long()


def _seen_everywhere(colour_fn):
    """A point-colour function as the bake takes it: every camera sees every point."""
    return lambda x, d: (colour_fn(x, d), torch.ones(len(x), dtype=torch.bool))


def _sample_texture(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear reads at ``uv`` as a renderer makes them (texel centres at (i + 0.5) / S), the
    texture clamped at its edges (the exported sampler's wrap)."""
    grid = (uv * 2 - 1).view(1, -1, 1, 2).float()
    image = texture.permute(2, 0, 1)[None].float()
    return torch.nn.functional.grid_sample(image, grid, align_corners=False, padding_mode="border").view(3, -1).T


def test_a_square_of_two_triangles_covers_every_texel_and_places_each_centre():
    uv = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    cover = rasterise_uv(uv, faces, 16)
    assert (cover.face >= 0).all()
    row, column = torch.meshgrid(torch.arange(16), torch.arange(16), indexing="ij")
    centres = torch.stack([(column + 0.5) / 16, (row + 0.5) / 16], dim=-1)
    rebuilt = (cover.barycentric[..., None] * uv[faces[cover.face]]).sum(dim=2)
    assert torch.allclose(rebuilt, centres, atol=1e-6)


def test_a_triangle_between_texel_centres_covers_none_and_dilation_stops_at_its_rings():
    cover = rasterise_uv(torch.tensor([[0.01, 0.01], [0.02, 0.01], [0.01, 0.02]]), torch.tensor([[0, 1, 2]]), 8)
    assert (cover.face < 0).all()
    image = torch.zeros(9, 9, 3)
    image[4, 4] = torch.tensor([0.2, 0.4, 0.6])
    filled = torch.zeros(9, 9, dtype=torch.bool)
    filled[4, 4] = True
    grown = dilate(image, filled, 2)
    assert torch.allclose(grown[2:7, 2:7], torch.tensor([0.2, 0.4, 0.6]).expand(5, 5, 3))
    assert (grown[:2] == 0).all() and (grown[:, 7:] == 0).all()  # three rings away: untouched


def test_decimation_keeps_the_budget_the_sphere_and_outward_normals():
    vertices, faces = _sphere_mesh()
    small_vertices, small_faces = decimate(vertices, faces, 1500)
    assert len(small_faces) <= 1500 < len(faces)
    assert (small_vertices.norm(dim=1) - RADIUS).abs().max() < 0.01  # measured: 0.0036
    normals = vertex_normals(small_vertices, small_faces)
    cosine = (normals * small_vertices).sum(dim=1) / small_vertices.norm(dim=1)
    assert cosine.min() > 0.95  # measured: 0.989
    assert decimate(vertices, faces, 10**6)[1] is faces
    with pytest.raises(NerfError, match="at least 4 triangles"):
        decimate(vertices, faces, 3)


def test_a_surface_of_many_open_pieces_is_brought_within_the_budget():
    """A noise field's level set (hundreds of pieces, open where they meet the volume's side):
    one pass of the simplifier stops at 319 faces for a budget of 300 (measured)."""
    noise = torch.randn(1, 1, 12, 12, 12, generator=torch.Generator().manual_seed(0))
    volume = torch.nn.functional.interpolate(noise, size=(48, 48, 48), mode="trilinear")[0, 0].numpy()
    vertices, faces, _, _ = marching_cubes(volume, 0.0)
    vertices, faces = torch.from_numpy(vertices.copy()), torch.from_numpy(faces.copy()).long()
    one_pass = fast_simplification.simplify(vertices.double().numpy(), faces.numpy(), target_count=300)[1]
    assert len(one_pass) > 300  # the case this guards
    small_vertices, small_faces = decimate(vertices, faces, 300)
    assert 250 < len(small_faces) <= 300  # the budget kept, and spent
    assert int(small_faces.max()) < len(small_vertices) and int(small_faces.min()) >= 0


def test_a_baked_position_field_reads_back_from_the_glb_where_the_surface_is(tmp_path):
    """colour(x, d) = (x + 1) / 2: the texture, read at any point of any triangle through the
    glTF file's own UVs, gives back that point's position, within what the texels resolve."""
    vertices, faces = _sphere_mesh()
    vertices, faces = decimate(vertices, faces, 2000)
    normals = vertex_normals(vertices, faces)
    atlas = unwrap(vertices, faces, 256)
    atlas_vertices = vertices[atlas.source_vertex]
    cover = rasterise_uv(atlas.uv, atlas.faces, 256)
    cameras = torch.from_numpy(np.asarray(fibonacci_sphere(50))).float() * 4.0
    baked = bake_texels(_seen_everywhere(lambda x, d: (x + 1) / 2), atlas_vertices, normals[atlas.source_vertex], atlas.faces, cover,
                        cameras)
    texture = dilate(baked.colours, baked.filled, GUTTER_TEXELS)
    path = tmp_path / "sphere.glb"
    size = write_glb(path, atlas_vertices, normals[atlas.source_vertex], atlas.uv, atlas.faces, texture, "sphere")
    assert size == path.stat().st_size

    document = pygltflib.GLTF2().load(str(path))
    blob = document.binary_blob()

    def read(accessor_index: int, dtype, width: int) -> np.ndarray:
        accessor = document.accessors[accessor_index]
        view = document.bufferViews[accessor.bufferView]
        return np.frombuffer(blob[view.byteOffset:view.byteOffset + view.byteLength], dtype).reshape(-1, width)

    primitive = document.meshes[0].primitives[0]
    positions = read(primitive.attributes.POSITION, np.float32, 3)
    blender = np.stack([positions[:, 0], -positions[:, 2], positions[:, 1]], axis=1)  # glTF Y-up to Blender Z-up
    assert np.allclose(blender, atlas_vertices.numpy(), atol=1e-6)
    triangles = torch.from_numpy(read(primitive.indices, np.uint32, 3).astype(np.int64))
    assert torch.equal(triangles, atlas.faces)
    uv = torch.from_numpy(read(primitive.attributes.TEXCOORD_0, np.float32, 2).copy())
    material = document.materials[primitive.material]
    assert UNLIT in document.extensionsUsed and UNLIT in material.extensions
    sampler = document.samplers[document.textures[material.pbrMetallicRoughness.baseColorTexture.index].sampler]
    assert sampler.wrapS == sampler.wrapT == CLAMP_TO_EDGE  # charts reach the edges: repeat would mix far charts
    image = document.images[document.textures[material.pbrMetallicRoughness.baseColorTexture.index].source]
    view = document.bufferViews[image.bufferView]
    png = iio.imread(blob[view.byteOffset:view.byteOffset + view.byteLength])
    assert png.shape == (256, 256, 3)
    read_back = torch.from_numpy(png.astype(np.float32) / 255)

    generator = torch.Generator().manual_seed(0)
    exponential = -torch.rand(40000, 3, generator=generator).log()
    weights = exponential / exponential.sum(dim=1, keepdim=True)  # uniform over each triangle
    chosen = torch.randint(len(triangles), (40000,), generator=generator)
    corners = triangles[chosen]
    points = (weights[..., None] * atlas_vertices[corners].float()).sum(dim=1)
    texel_uv = (weights[..., None] * uv[corners]).sum(dim=1)
    error = (_sample_texture(read_back, texel_uv) - (points + 1) / 2).abs()
    # A texel spans about 0.013 of the sphere's surface (its area over the covered texels), so
    # the colour, half the position, is resolved to about 0.007 plus 8-bit rounding; measured:
    # mean 0.00065, largest 0.0060 (0.049 before the texture was clamped at its edges: a point
    # of a chart at the edge read the opposite edge's texels, as glTF's default repeat does).
    assert error.mean() < 0.002 and error.max() < 0.015


def test_view_dependent_colour_bakes_to_the_facing_views_average():
    """colour(x, d) = cosine between d and the inward normal: the cameras chosen face each
    texel squarely, so the bake is near 1 everywhere. (A camera looking edge-on gives 0; every
    camera in front, cosine-weighted, would average 2/3.)"""
    vertices, faces = _sphere_mesh(32)
    atlas = unwrap(vertices, faces, 128)
    normals = vertex_normals(vertices, faces)[atlas.source_vertex]
    cover = rasterise_uv(atlas.uv, atlas.faces, 128)
    cameras = torch.from_numpy(np.asarray(fibonacci_sphere(100))).float() * 4.0

    def facing(x, d):
        return (-(d * torch.nn.functional.normalize(x, dim=1)).sum(dim=1, keepdim=True)).expand(-1, 3)

    baked = bake_texels(_seen_everywhere(facing), vertices[atlas.source_vertex], normals, atlas.faces, cover, cameras)
    values = baked.colours[baked.filled][:, 0]
    # Measured: mean 0.890, least 0.877 (the 8 most squarely facing of 100 cameras on a sphere
    # of 4 radii about the ball of 0.7).
    assert values.mean() > 0.85 and values.min() > 0.83


# A floor with a block standing on it: (box min, box max, colour).
FLOOR = ((-1.0, -1.0, -0.3), (1.0, 1.0, 0.0), (1.0, 0.2, 0.2))
BLOCK = ((-0.3, -0.3, 0.0), (0.3, 0.3, 0.5), (0.2, 0.2, 1.0))


def _render_boxes(origins, directions, t_near, t_far):
    """FLOOR and BLOCK as opaque solids, rendered as bake.RenderFn returns it: the colour of
    the first box a stretch of ray meets (at its start where it starts inside one), opacity
    1 there and that distance."""
    first = torch.full_like(t_near, math.inf)
    colour = torch.zeros_like(origins)
    inverse = 1 / torch.where(directions.abs() < 1e-9, torch.full_like(directions, 1e-9), directions)
    for low, high, box_colour in (FLOOR, BLOCK):
        near = (torch.tensor(low) - origins) * inverse
        far = (torch.tensor(high) - origins) * inverse
        enter = torch.minimum(near, far).amax(dim=1).clamp_min(t_near)
        leave = torch.maximum(near, far).amin(dim=1)
        hit = (enter <= leave) & (enter <= t_far) & (enter < first)
        first = torch.where(hit, enter, first)
        colour[hit] = torch.tensor(box_colour)
    hit = first.isfinite()
    return colour, hit.float(), torch.where(hit, first, torch.zeros_like(first))


def test_texels_in_a_crease_take_their_own_surfaces_colour():
    """Where a block stands on a floor, cameras that face the floor near it look past the
    block: within the bake's reach before the point their ray is inside the block, and what
    they render there is the block. They must not count."""
    cells = 48
    axis = torch.linspace(-1, 1, cells, dtype=torch.float64)
    points = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"))

    def inside(low, high):  # positive inside the box
        return torch.stack([torch.minimum(points[i] - low[i], high[i] - points[i]) for i in range(3)]).amin(dim=0)

    solid = torch.maximum(inside(*FLOOR[:2]), inside(*BLOCK[:2]))
    vertices, faces, _, _ = marching_cubes(solid.numpy(), 0.0, spacing=(2 / (cells - 1),) * 3)
    vertices, faces = torch.from_numpy(vertices.copy()) - 1.0, torch.from_numpy(faces[:, [0, 2, 1]].copy()).long()
    atlas = unwrap(vertices, faces, 256)
    normals = vertex_normals(vertices, faces)[atlas.source_vertex]
    cover = rasterise_uv(atlas.uv, atlas.faces, 256)
    sphere = torch.from_numpy(np.asarray(fibonacci_sphere(200))).float()
    cameras = sphere[sphere[:, 2] > 0.1] * 4.0  # the upper hemisphere, as the datasets' cameras
    seen = colour_seen_near(_render_boxes, reach=0.3)  # seven of the mesh's cells
    atlas_vertices = vertices[atlas.source_vertex]
    baked = bake_texels(seen, atlas_vertices, normals, atlas.faces, cover, cameras)
    texel = _texel_points(atlas_vertices, atlas.faces, cover)
    on_block = (texel[:, 2] > 0.01) & (texel[:, :2].abs().amax(dim=1) < 0.31)
    on_floor = (texel[:, 2] > -0.01) & (texel[:, :2].abs().amax(dim=1) > 0.32)
    own = torch.where(on_block[:, None], torch.tensor(BLOCK[2]), torch.tensor(FLOOR[2]))
    near_crease = (on_block | on_floor) & (texel[:, 2] < 0.15) & ((texel[:, :2].abs().amax(dim=1) - 0.3).abs() < 0.15)

    def wrong(texture) -> float:
        error = (texture.colours[texture.filled] - own).abs().amax(dim=1)
        return float((error[near_crease] > 0.05).float().mean())

    everyone = bake_texels(lambda x, d: (seen(x, d)[0], torch.ones(len(x), dtype=torch.bool)),
                           atlas_vertices, normals, atlas.faces, cover, cameras)
    # Measured: 0.03 % of the 3 280 texels near the crease off by more than 0.05; with every
    # camera counted as if it saw the point, 19 %.
    assert wrong(baked) < 0.01 and wrong(everyone) > 0.05


def _texel_points(vertices, faces, cover):
    filled = cover.face >= 0
    corners = faces[cover.face[filled]]
    return (cover.barycentric[filled].to(vertices.dtype)[..., None] * vertices[corners]).sum(dim=1).float()


def test_a_trained_surface_run_exports_through_the_cli(trained_surface_run, tmp_path):
    out = tmp_path / "asset.glb"
    result = run_python("-m", "nerf_backend", "export", str(trained_surface_run), "--out", str(out),
                        "--triangles", "3000", "--texture-size", "256", "--resolution", "96", "--no-progress")
    assert "export:" in result.stdout
    record = json.loads((tmp_path / "asset.glb.json").read_text())
    assert record["triangles"] <= 3000 < record["surface_triangles"]
    assert record["bytes"] == out.stat().st_size and record["texture_size"] == 256
    assert record["surface"]["threshold_rule"] == "the signed distance's zero level set"
    document = pygltflib.GLTF2().load(str(out))
    accessor = document.accessors[document.meshes[0].primitives[0].attributes.POSITION]
    # In Blender's world: the demo's objects lie within its scene profile's bounds (Blender
    # metres; the NeRF frame is scaled) – checked on the glTF's bounds, turned back Z-up.
    profile = json.loads((trained_surface_run / "config.json").read_text())
    dataset = profile["dataset"]
    scene = json.loads((__import__("pathlib").Path(dataset) / "scene_profile.json").read_text())
    sphere = scene["world_to_nerf"]["sphere_blender"]
    low = np.array([accessor.min[0], -accessor.max[2], accessor.min[1]])
    high = np.array([accessor.max[0], -accessor.min[2], accessor.max[1]])
    centre, radius = np.array(sphere["centre"]), sphere["radius"]
    assert (np.abs(low - centre) < radius * 1.2).all() and (np.abs(high - centre) < radius * 1.2).all()
    again = run_python("-m", "nerf_backend", "export", str(trained_surface_run), "--out", str(out), check=False)
    assert again.returncode == 2 and "exists; pass --overwrite" in again.stderr
    wrong = run_python("-m", "nerf_backend", "export", str(trained_surface_run), "--out", str(tmp_path / "a.obj"),
                       check=False)
    assert wrong.returncode == 2 and "glTF binary, .glb" in wrong.stderr
    small = run_python("-m", "nerf_backend", "export", str(trained_surface_run), "--out", str(tmp_path / "b.glb"),
                       "--texture-size", "16", check=False)
    assert small.returncode == 2 and "between 64 and 8192 texels" in small.stderr
    assert not (tmp_path / "b.glb").exists() and math.isfinite(record["seconds"]["bake"])
