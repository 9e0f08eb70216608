"""Rays bent through the scene's glass (core/refraction.py, model_components/glass.py),
against optics worked out by hand: a slab shifts a ray without turning it, a right-angle prism
turns it by total internal reflection, a ball's centre ray goes straight; the compiled walk of the
hierarchy finds what testing every triangle finds; and the model marches the field beyond the
glass with the gradients reaching it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from nerf_backend.core.mesh_normals import corner_normals
from nerf_backend.core.refraction import build_bvh, fresnel_reflectance, nearest_triangle_hits
from nerf_backend.data.occupancy_prior import OccupancyPrior, smooth_glass
from nerf_backend.kernels.build import load_kernel
from nerf_backend.model_components.glass import SURFACE_OFFSET, GlassSurfaces

IOR = 1.5


def _box(low, high) -> np.ndarray:
    """[12, 3, 3] the triangles of an axis-aligned box."""
    x0, y0, z0 = low
    x1, y1, z1 = high
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], np.float32)
    quads = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (1, 2, 6, 5), (0, 4, 7, 3)]
    return np.stack([v[[a, b, c]] for a, b, c, d in quads] + [v[[a, c, d]] for a, b, c, d in quads])


def _glass(triangles: np.ndarray, smooth: bool = False) -> GlassSurfaces:
    vertices, faces = np.unique(triangles.reshape(-1, 3), axis=0, return_inverse=True)
    faces = faces.reshape(-1, 3)
    normals = corner_normals(vertices, faces, smooth_angle_deg=180.0 if smooth else 1.0)
    glass = GlassSurfaces()
    glass.set(torch.from_numpy(vertices[faces]), torch.from_numpy(normals).float(), torch.full((len(faces),), IOR))
    return glass


def _sphere(radius: float, rings: int = 48, segments: int = 96) -> np.ndarray:
    theta = np.linspace(0, math.pi, rings + 1)
    phi = np.linspace(0, 2 * math.pi, segments + 1)
    p = radius * np.stack([np.sin(theta)[:, None] * np.cos(phi), np.sin(theta)[:, None] * np.sin(phi),
                           np.cos(theta)[:, None] * np.ones_like(phi)], axis=-1)
    quads = [(p[i, j], p[i + 1, j], p[i + 1, j + 1], p[i, j + 1]) for i in range(rings) for j in range(segments)]
    triangles = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    triangles = [t for t in triangles if np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) > 1e-12]
    return np.asarray(triangles, np.float32)


@pytest.mark.parametrize("degrees", [0.0, 20.0, 45.0, 70.0])
def test_a_slab_shifts_a_ray_sideways_without_turning_it(degrees):
    thickness = 0.4
    glass = _glass(_box((-5, -5, 0.0), (5, 5, thickness)))
    angle = math.radians(degrees)
    direction = torch.tensor([[math.sin(angle), 0.0, math.cos(angle)]])
    paths = glass.trace(torch.tensor([[0.0, 0.0, -1.0]]), direction)
    assert paths.rays.tolist() == [0] and paths.t_entry.item() == pytest.approx(1.0 / math.cos(angle), rel=1e-5)
    leaving, reflected = paths.directions
    assert torch.allclose(leaving, direction[0], atol=1e-5)
    assert torch.allclose(reflected, torch.tensor([math.sin(angle), 0.0, -math.cos(angle)]), atol=1e-5)
    # Snell: inside at θt, sin θt = sin θ / n; the exit lies thickness · tan θt further along x.
    inside = math.asin(math.sin(angle) / IOR)
    entry_x = math.tan(angle)
    # The leaving ray starts SURFACE_OFFSET of the glass's size (1.4e-3 here) beyond the exit.
    exit_point = paths.origins[0] - SURFACE_OFFSET * math.sqrt(200 + thickness ** 2) * leaving
    assert exit_point[2].item() == pytest.approx(thickness, abs=1e-5)
    assert exit_point[0].item() == pytest.approx(entry_x + thickness * math.tan(inside), abs=1e-5)
    # Fresnel: 4 % head on for n = 1.5; more at a slant.
    assert paths.fresnel.item() == pytest.approx(float(fresnel_reflectance(
        direction, torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([1 / IOR]))[0]), abs=1e-6)
    assert (paths.fresnel.item() == pytest.approx(0.04, abs=1e-4)) == (degrees == 0.0)


def test_a_right_angle_prism_turns_a_ray_by_total_internal_reflection():
    # A prism along y, its cross-section the triangle (0, 0), (1, 0), (0, 1) in (x, z): the right
    # angle between the faces z = 0 and x = 0, the hypotenuse x + z = 1.
    a, b, c = np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([0.0, 1.0])  # (x, z)
    def p(xz, y):
        return [xz[0], y, xz[1]]
    triangles = []
    for (u, v) in ((a, b), (b, c), (c, a)):  # the three rectangular faces
        triangles += [[p(u, -2), p(v, -2), p(v, 2)], [p(u, -2), p(v, 2), p(u, 2)]]
    triangles += [[p(a, -2), p(c, -2), p(b, -2)], [p(a, 2), p(b, 2), p(c, 2)]]
    glass = _glass(np.asarray(triangles, np.float32))
    # Into the face z = 0 from below, straight up: it meets the hypotenuse at 45° (past the
    # critical angle of 41.8°), is turned to -x, and leaves through the face x = 0 straight.
    paths = glass.trace(torch.tensor([[0.3, 0.0, -1.0]]), torch.tensor([[0.0, 0.0, 1.0]]))
    leaving = paths.directions[0]
    assert torch.allclose(leaving, torch.tensor([-1.0, 0.0, 0.0]), atol=1e-5)
    assert paths.origins[0, 0].item() == pytest.approx(0.0, abs=1e-3)
    assert paths.origins[0, 2].item() == pytest.approx(0.7, abs=1e-3)


def test_a_balls_centre_ray_goes_straight_and_its_rim_is_bent():
    glass = _glass(_sphere(1.0), smooth=True)
    origins = torch.tensor([[0.0, 0.0, -3.0], [0.5, 0.0, -3.0], [3.0, 0.0, -3.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    paths = glass.trace(origins, directions)
    assert paths.rays.tolist() == [0, 1]
    straight, bent = paths.directions[0], paths.directions[1]
    assert torch.allclose(straight, torch.tensor([0.0, 0.0, 1.0]), atol=1e-4)
    # A ray at height h through a ball of radius 1 turns by 2(θ - θt), θ = asin(h), sin θt = h / n.
    h = 0.5
    turn = 2 * (math.asin(h) - math.asin(h / IOR))
    assert math.degrees(math.acos(bent[2].item())) == pytest.approx(math.degrees(turn), abs=0.3)
    assert bent[0].item() < 0  # towards the axis


@pytest.mark.skipif(load_kernel("ray_mesh")[0] is None, reason="no C compiler: the torch path alone")
def test_the_compiled_walk_finds_what_every_triangle_finds():
    generator = torch.Generator().manual_seed(0)
    triangles = np.concatenate([_sphere(0.8, 12, 24), _box((-1.0, -0.2, -0.3), (0.4, 0.9, 0.1)),
                                (torch.rand((200, 3, 3), generator=generator).numpy() * 2 - 1).astype(np.float32)])
    glass = _glass(triangles)
    origins = torch.rand((3000, 3), generator=generator) * 6 - 3
    targets = torch.rand((3000, 3), generator=generator) * 2 - 1  # most rays meet something
    directions = torch.nn.functional.normalize(targets - origins, dim=1)
    for t_min in (0.0, 0.5):
        compiled = glass._hits(origins, directions, t_min)
        every = nearest_triangle_hits(origins, directions, glass.corners, t_min)
        found = torch.isfinite(every[0])
        assert found.sum() > 1500 and torch.equal(torch.isfinite(compiled[0]), found)
        assert torch.allclose(compiled[0][found], every[0][found], atol=1e-5)
        same_face = compiled[1][found] == every[1][found]
        assert same_face.float().mean() > 0.999  # a tie at a shared edge may go either way
        assert torch.allclose(compiled[2][found][same_face], every[2][found][same_face], atol=1e-4)


def test_the_hierarchy_holds_every_triangle_once_inside_its_nodes_bounds():
    triangles = _sphere(1.0, 10, 20)
    lo, hi, child, order = build_bvh(triangles)
    assert sorted(order.tolist()) == list(range(len(triangles)))
    for node, (first, count) in enumerate(child.tolist()):
        if first < 0:
            held = triangles[order[-first - 1:-first - 1 + count]]
            assert (held.min(axis=(0, 1)) >= lo[node] - 1e-6).all() and (held.max(axis=(0, 1)) <= hi[node] + 1e-6).all()


@pytest.mark.parametrize("with_materials", [True, False])
def test_glass_faces_are_the_glass_materials_or_else_those_in_transmissive_cells(tmp_path, with_materials):
    from datasets_gen.io.surface_mesh import weld, write_ply_atomic

    cube = _box((0.1, 0.1, 0.1), (0.4, 0.4, 0.4))  # green glass (material 2), in the transmissive cells
    floor = _box((-1.0, -1.0, -1.0), (1.0, 1.0, -0.9))  # diffuse (material 0), across the whole box
    inner = _box((0.2, 0.2, 0.2), (0.3, 0.3, 0.3))  # a diffuse thing inside the glass (material 1)
    materials = np.array([2] * 12 + [0] * 12 + [1] * 12)
    write_ply_atomic(str(tmp_path / "scene_geometry.ply"),
                     *weld(np.concatenate([cube, floor, inner]), materials if with_materials else None))
    regions = torch.zeros((8, 8, 8), dtype=torch.uint8)
    regions[:, :, :1] = 1  # diffuse
    regions[4:7, 4:7, 4:7] = 5  # transmissive: [0, 0.75]³
    green = (0.2, 0.8, 0.3)
    prior = OccupancyPrior(regions > 0, (-1.0, -1.0, -1.0), 0.25, "surface", regions=regions,
                           geometry=tmp_path / "scene_geometry.ply", glass_materials={2: (1.45, green)},
                           all_transmissive_glass=True)
    corners, normals, ior, glass, colours = prior.glass_surfaces()
    # From each face's material, the cube alone; from the cells, the thing inside it too.
    glass_faces = 12 if with_materials else 24
    assert corners.shape == (glass_faces, 3, 3) and normals.shape == (glass_faces, 3, 3)
    assert torch.allclose(ior, torch.full((glass_faces,), 1.45)) and glass.tolist() == [0] * glass_faces
    assert torch.allclose(colours, torch.tensor([green]))
    assert corners.min().item() == pytest.approx(0.1) and corners.max().item() == pytest.approx(0.4)
    prior.glass_materials = {}  # no glass: nothing is bent
    assert prior.glass_surfaces() is None
    if not with_materials:  # cells alone cannot tell glass from a rough transmissive material beside it
        prior.glass_materials, prior.all_transmissive_glass = {2: (1.45, green)}, False
        assert prior.glass_surfaces() is None


def test_two_glasses_each_keep_their_ior_and_tint(tmp_path):
    from datasets_gen.io.surface_mesh import weld, write_ply_atomic

    write_ply_atomic(str(tmp_path / "scene_geometry.ply"),
                     *weld(np.concatenate([_box((0.1, 0.1, 0.1), (0.4, 0.4, 0.4)),
                                           _box((-0.6, -0.6, -0.6), (-0.3, -0.3, -0.3))]),
                           np.array([4] * 12 + [7] * 12)))
    prior = OccupancyPrior(torch.ones((8, 8, 8), dtype=torch.bool), (-1.0, -1.0, -1.0), 0.25, "surface",
                           geometry=tmp_path / "scene_geometry.ply",
                           glass_materials={4: (1.33, (1.0, 1.0, 1.0)), 7: (1.5, (0.9, 0.2, 0.2))})
    corners, _, ior, glass, colours = prior.glass_surfaces()
    low = corners.mean(dim=(1, 2)) < 0
    assert torch.allclose(ior[low], torch.tensor(1.5)) and torch.allclose(ior[~low], torch.tensor(1.33))
    assert colours[glass[low]].tolist() == [[0.8999999761581421, 0.20000000298023224, 0.20000000298023224]] * 12
    surfaces = GlassSurfaces()
    surfaces.set(*prior.glass_surfaces())
    # The light through the red glass starts at its colour squared (in and out), the clear one's at 1.
    paths = surfaces.trace(torch.tensor([[-0.45, -0.45, -3.0], [0.25, 0.25, 3.0]]),
                           torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    assert torch.allclose(paths.tint, torch.tensor([[0.81, 0.04, 0.04], [0.999, 0.999, 0.999]]), atol=1e-4)
    assert surfaces.tint_logits.requires_grad


def test_only_smooth_fully_transmissive_nearly_colourless_unmixed_glass_is_bent():
    def material(transmission=1.0, roughness=0.0, ior=1.45, region="transmissive", colour=(1.0, 1.0, 1.0)):
        return {"region": region, "appearance": {"inputs": {
            "transmission": {"value": transmission}, "roughness": {"value": roughness}, "ior": {"value": ior},
            "base_colour": {"value": list(colour)}}}}
    assert smooth_glass(material()) == (1.45, (1.0, 1.0, 1.0)) and smooth_glass(material(ior=1.33))[0] == 1.33
    assert smooth_glass(material(colour=(0.95, 1.0, 0.9))) == (1.45, (0.95, 1.0, 0.9))  # nearly colourless
    assert smooth_glass(material(colour=(0.8, 0.95, 0.9))) is None  # glass_and_gloss's green cube
    no_colour = material()
    del no_colour["appearance"]["inputs"]["base_colour"]  # a profile from before the base colour was read
    assert smooth_glass(no_colour) is None
    assert smooth_glass(material(transmission=0.3)) is None  # 20_specular's: partly transmissive
    assert smooth_glass(material(roughness=0.5)) is None
    varies = material()
    varies["appearance"]["inputs"]["transmission"] = {"varies": "driven by an Image Texture"}
    assert smooth_glass(varies) is None
    textured = material()
    textured["appearance"]["inputs"]["base_colour"] = {"varies": "driven by the Image Texture node 'Label'"}
    assert smooth_glass(textured) is None
    with_volume = material()  # glTF-Blender-IO's 16_volume.blend: tinted by the depth crossed
    with_volume["appearance"]["other_shaders"] = ["volume 'Volume Absorption'"]
    assert smooth_glass(with_volume) is None
    with_volume["appearance"]["other_shaders"] = []
    assert smooth_glass(with_volume) == (1.45, (1.0, 1.0, 1.0))
    assert smooth_glass(material(region="diffuse")) is None and smooth_glass(None) is None


def test_a_model_marches_the_field_beyond_the_glass_with_gradients_reaching_it():
    """The grid model with ``refraction``: a ray that meets the glass is the field up to it over
    what shows there, (1 − F) of the field along the ray leaving it and F along the reflected one,
    each marched as any ray is, over the world's light where they leave; a ray that misses it is
    marched as without glass; and in training the loss of the rays that meet the glass reaches
    the field's parameters and the world's."""
    from conftest import rays_through_box

    from nerf_backend.configs.presets import PRESETS
    from nerf_backend.core.cameras import ray_box_intersection
    from nerf_backend.core.scene_bounds import SceneBounds
    from nerf_backend.models.registry import build_model

    box = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    torch.manual_seed(3)
    model = build_model(dataclasses.replace(PRESETS["fast"], refraction=True), box)
    with torch.no_grad():
        for parameter in model.field.encoding_parameters():
            parameter.normal_(0.0, 0.5)
    model.update_occupancy()
    ball = _glass(_sphere(0.4, 16, 32), smooth=True)
    model.glass.set(ball.corners, ball.normals, ball.ior, torch.zeros(len(ball.ior), dtype=torch.long),
                    torch.tensor([[0.9, 0.8, 0.7]]))
    origins, directions, near, far = rays_through_box(box, 400, seed=4)
    model.eval()
    with torch.no_grad():
        rendered = model(origins, directions, near, far, background=1.0)[0]
        paths = model.glass.trace(origins, directions)
        met = paths.rays
        assert 40 < met.numel() < 360
        _, beyond_far, _ = ray_box_intersection(paths.origins, paths.directions, model.field.box_min,
                                                model.field.box_max)
        beyond = model._march_rays(paths.origins, paths.directions, torch.zeros_like(beyond_far), beyond_far,
                                   model.environment(paths.directions), None)[0]
        up_to = model._march_rays(origins[met], directions[met], near[met], torch.minimum(far[met], paths.t_entry),
                                  0.0, None)[0]
        expected = up_to.rgb + (1.0 - up_to.opacity)[:, None] * paths.colour_seen(beyond.rgb)
        assert torch.allclose(rendered.rgb[met], expected, atol=1e-5)
        missed = torch.ones(len(origins), dtype=torch.bool).index_fill(0, met, False)
        straight = model._march_rays(origins[missed], directions[missed], near[missed], far[missed], 1.0, None)[0]
        assert torch.allclose(rendered.rgb[missed], straight.rgb, atol=1e-6)
    model.train()
    trained = model(origins[met], directions[met], near[met], far[met], background=1.0)[0]
    trained.rgb.sum().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.field.encoding_parameters())
    # The world seen through the glass, and the glass's tint, are learned with the networks.
    assert model.environment.harmonics.grad.abs().sum() > 0 and model.glass.tint_logits.grad.abs().sum() > 0
    networks = next(group for group in model.parameter_groups() if group.name == "networks")
    assert any(p is model.environment.harmonics for p in networks.parameters)
    assert any(p is model.glass.tint_logits for p in networks.parameters)


def test_the_cells_of_glass_alone_are_left_empty_for_the_field(tmp_path):
    """Where rays are bent through the glass the field holds nothing at it: the prior's cells
    near the glass and no other surface are emptied; those near another surface stay."""
    from datasets_gen.io.surface_mesh import weld, write_ply_atomic

    cube = _box((0.1, 0.1, -0.9), (0.6, 0.6, 0.4))  # glass standing on the floor
    floor = _box((-1.0, -1.0, -1.0), (1.0, 1.0, -0.9))
    write_ply_atomic(str(tmp_path / "scene_geometry.ply"),
                     *weld(np.concatenate([cube, floor]), np.array([1] * 12 + [0] * 12)))
    occupied = torch.ones((16, 16, 16), dtype=torch.bool)
    prior = OccupancyPrior(occupied, (-1.0, -1.0, -1.0), 0.125, "surface", margin_cells=1,
                           geometry=tmp_path / "scene_geometry.ply", glass_materials={1: (1.45, (1.0, 1.0, 1.0))})
    emptied = ~prior.without_glass().occupied
    centre = (torch.nonzero(emptied).float() + 0.5) * 0.125 - 1.0
    assert emptied.sum() > 100
    # Every emptied cell lies by the glass, more than a grown cell above the floor.
    assert (centre[:, 2] > -0.9 + 2 * 0.125).all()
    assert ((centre[:, :2] > 0.1 - 3 * 0.125) & (centre[:, :2] < 0.6 + 3 * 0.125)).all()
    # The glass's top face's cells are empty; far cells and the floor's stay.
    assert emptied[9, 9, 11] and not emptied[0, 0, 0] and not emptied[9, 9, 0] and not emptied[15, 15, 15]
    prior.glass_materials = {}
    assert prior.without_glass() is prior


@pytest.mark.parametrize("bodies", [1, 2])
def test_a_ray_through_two_panes_is_traced_through_each(monkeypatch, bodies):
    """A glass dish's floor seen through its wall: a ray that leaves one piece of glass and meets
    another is traced through that one too (``GLASS_BODIES`` pieces a path). Two horizontal
    panes over an empty field on a uniform world ``c``, rays straight down: at normal incidence
    each pane passes (1 − F) of the light (F = ((n − 1)/(n + 1))² = 0.04 at n = 1.5) tinted by T
    and reflects F of the world, so the pixel is (1 − F)·T·((1 − F)·T·c + F·c) + F·c through
    both, and (1 − F)·T·c + F·c where only the first is traced."""
    import nerf_backend.models.marched as marched
    from nerf_backend.configs.presets import PRESETS
    from nerf_backend.core.scene_bounds import SceneBounds
    from nerf_backend.models.registry import build_model

    monkeypatch.setattr(marched, "GLASS_BODIES", bodies)
    box = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    model = build_model(dataclasses.replace(PRESETS["fast"], refraction=True), box)
    model.occupancy.mark(torch.zeros(model.occupancy.cells, dtype=torch.bool))  # nothing but the glass
    panes = _glass(np.concatenate([_box((-0.8, -0.8, 0.30), (0.8, 0.8, 0.35)),
                                   _box((-0.8, -0.8, -0.35), (0.8, 0.8, -0.30))]))
    tint = torch.tensor([[0.9, 0.8, 0.7]])
    model.glass.set(panes.corners, panes.normals, panes.ior, torch.zeros(len(panes.ior), dtype=torch.long), tint)
    world = torch.tensor([0.6, 0.5, 0.4])
    model.environment.start_at(tuple(world.tolist()))
    xy = torch.rand((64, 2), generator=torch.Generator().manual_seed(5)) - 0.5
    origins = torch.cat([xy, torch.full((64, 1), 0.9)], dim=1)
    directions = torch.tensor([0.0, 0.0, -1.0]).expand(64, 3).contiguous()
    model.eval()
    with torch.no_grad():
        rendered = model(origins, directions, torch.zeros(64), torch.full((64,), 1.9), background=1.0)[0]
    fresnel, through = ((IOR - 1.0) / (IOR + 1.0)) ** 2, tint[0] ** 2  # tinted in and out of each pane
    beyond_first = (1 - fresnel) * through * world + fresnel * world if bodies == 2 else world
    expected = (1 - fresnel) * through * beyond_first + fresnel * world
    assert torch.allclose(rendered.rgb, expected.expand(64, 3), atol=2e-3), (rendered.rgb[0], expected)


def _shell(low, high, wall) -> np.ndarray:
    """A closed box of glass walls ``wall`` thick: the outer box, and the inner one turned inside out."""
    inner = _box(np.asarray(low) + wall, np.asarray(high) - wall)
    return np.concatenate([_box(low, high), inner[:, ::-1]])


def test_thin_walled_glass_goes_straight_and_only_thick_glass_is_bent(tmp_path):
    """A glass dish's walls shift a ray by under their width, which a view-dependent colour
    learns; bent, its rims and silhouette are what the bent rays cannot show (a dish with olives
    at 100×100: 32.78 dB straight, 25.72 bent). So each body of smooth glass is measured
    (``wall_share``: its mean chord 4V/S over its size): a closed box of walls 0.02 thick is
    left to the field; a solid cube of the same glass beside it is bent; and where all glass is
    thin the plan says so and sends the rays straight."""
    from datasets_gen.io.surface_mesh import weld, write_ply_atomic

    from nerf_backend.core.mesh_shape import wall_share
    from nerf_backend.data.occupancy_prior import GLASS_MIN_WALL_SHARE
    from nerf_backend.planning.plan import plan_run
    from nerf_backend.planning.rules import RULES, _example, auto_refraction

    shell, cube = _shell((-0.8, -0.8, -0.8), (0.0, 0.0, 0.0), 0.02), _box((0.2, 0.2, 0.2), (0.6, 0.6, 0.6))
    assert wall_share(shell) < 0.5 * GLASS_MIN_WALL_SHARE and wall_share(cube) > 3 * GLASS_MIN_WALL_SHARE
    occupied = torch.ones((16, 16, 16), dtype=torch.bool)

    def prior(*bodies: np.ndarray) -> OccupancyPrior:
        path = tmp_path / f"scene_geometry_{len(bodies)}.ply"
        write_ply_atomic(str(path), *weld(np.concatenate(bodies), np.zeros(sum(len(b) for b in bodies), int)))
        return OccupancyPrior(occupied, (-1.0, -1.0, -1.0), 0.125, "solid", geometry=path,
                              glass_materials={0: (1.5, (1.0, 1.0, 1.0))})

    both = prior(shell, cube)
    corners = both.glass_surfaces()[0].numpy()
    assert len(corners) == len(cube) and corners.min() >= 0.2 - 1e-6  # the cube's triangles alone
    assert list(both.thin_glass()) == [0] and len(both.thin_glass()[0]) == 1
    assert both.without_glass().occupied[2, 2, 2]  # the shell's cells stay the field's

    facts, _ = _example(before=auto_refraction)
    for glass, bent, says in ((both, True, "1 body of thin-walled glass"),
                              (prior(shell), False, "thin-walled (1 body,")):
        plan = plan_run(dataclasses.replace(facts, priors={"solid": glass}), RULES[:RULES.index(auto_refraction) + 1])
        assert plan.config.refraction is bent and says in plan.decisions["refraction"]["reason"]
