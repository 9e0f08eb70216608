"""A small procedural demo scene, built in code, that exercises what NeRFs find hard.

It sits at the origin within radius ~1.05, so the protocol's camera (radius 4.03, FOV 0.691 rad,
which sees about +-1.45 at the origin) frames it from every direction without clipping:
a diffuse pedestal, a glossy gold sphere (view-dependent highlights), a checker-textured cube
and a brick-textured cone (high-frequency texture), and a thin rod carrying a thin ring
(minor radius 0.03: thin structures). A world colour lights it from all around (the film is
transparent, so it is never seen directly) and a sun adds shadows.

The "diffuse" variant is the same scene with every material a pure Diffuse BSDF (same colours
and textures; no metallic, specular, clearcoat, sheen or transmission), so nothing in it
depends on the view direction: a benchmark for the backend's view-independent model.

Meshes are made with bmesh and the data API rather than operators, so the scene can be built
into a scene that is not the active one and the result never depends on UI context.
Everything is deterministic.

The building helpers below (a protocol-ready scene, a plain world, a sun, objects, materials and
meshes) are shared with the benchmark's trap scenes (`trap_scenes`); `builtin_scenes` is the
registry of every scene built in code.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import bmesh
import bpy
from mathutils import Euler

from .compat import diffuse_bsdf, node_tree_of, principled_bsdf, set_node_input

DEMO_SCENE_NAME = "NeRF demo"
PEDESTAL_TOP_Z = -0.5
TURNTABLE_FRAMES = 48
TURNTABLE_RADIUS = 3.0
TURNTABLE_HEIGHT = 1.3


def build_demo_scene(name: str = DEMO_SCENE_NAME, variant: str = "standard") -> "bpy.types.Scene":
    """Create a new scene holding the demo objects, world and sun; return it.

    `variant` is "standard" or "diffuse" (every material a Diffuse BSDF, see the module docstring).
    """
    if variant not in ("standard", "diffuse"):
        raise ValueError(f"unknown demo variant {variant!r}")
    diffuse = variant == "diffuse"
    scene = new_protocol_scene(name)
    # A plain sky-blue environment: lights the scene softly from every direction.
    scene.world = plain_world(name, (0.55, 0.60, 0.70), 0.6)

    pedestal = add_object(scene, "pedestal", cylinder_mesh("pedestal", 0.85, 0.12, 96),
                          (0.0, 0.0, PEDESTAL_TOP_Z - 0.06))
    assign(pedestal, make_material("pedestal", (0.55, 0.50, 0.45), roughness=0.8, diffuse=diffuse))

    sphere_radius = 0.32
    sphere = add_object(scene, "gold sphere", sphere_mesh("gold sphere", sphere_radius),
                        (0.38, -0.22, PEDESTAL_TOP_Z + sphere_radius))
    assign(sphere, make_material("gold", (1.0, 0.72, 0.30), roughness=0.15, metallic=1.0, diffuse=diffuse))

    cube_size = 0.5
    cube = add_object(scene, "checker cube", cube_mesh("checker cube", cube_size),
                      (-0.38, 0.18, PEDESTAL_TOP_Z + cube_size / 2.0), rotation_z_deg=30.0)
    assign(cube, textured_material("checker", "ShaderNodeTexChecker", (0.08, 0.22, 0.80),
                                    (0.92, 0.92, 0.92), scale=4.0, diffuse=diffuse))

    cone_height = 0.45
    cone = add_object(scene, "brick cone", cone_mesh("brick cone", 0.22, cone_height, 64),
                      (-0.22, -0.48, PEDESTAL_TOP_Z + cone_height / 2.0))
    assign(cone, textured_material("brick", "ShaderNodeTexBrick", (0.70, 0.22, 0.08),
                                    (0.95, 0.55, 0.20), scale=6.0, diffuse=diffuse))

    rod_length = 0.95
    rod_xy = (0.12, 0.38)
    rod = add_object(scene, "thin rod", cylinder_mesh("thin rod", 0.025, rod_length, 24),
                     (rod_xy[0], rod_xy[1], PEDESTAL_TOP_Z + rod_length / 2.0))
    assign(rod, make_material("rod", (0.60, 0.05, 0.05), roughness=0.4, diffuse=diffuse))

    ring_major = 0.25
    ring = add_object(scene, "thin ring", torus_mesh("thin ring", ring_major, 0.03),
                      (rod_xy[0], rod_xy[1], PEDESTAL_TOP_Z + rod_length + ring_major),
                      rotation_x_deg=90.0, rotation_z_deg=45.0)
    assign(ring, make_material("ring", (0.10, 0.60, 0.25), roughness=0.3, diffuse=diffuse))

    add_sun(scene, name, energy=3.0, rotation_x_deg=40.0, rotation_z_deg=30.0)
    add_turntable_camera(scene, (0.0, 0.0, PEDESTAL_TOP_Z + 0.55))

    scene.view_layers[0].update()
    return scene


def add_turntable_camera(scene: "bpy.types.Scene", target: Sequence[float]) -> "bpy.types.Object":
    """The scene's camera (`turntable camera`), animated for a camera-path demo: one turn around
    ``target`` over TURNTABLE_FRAMES frames at 24 fps, its lens zooming from 35 to 50 mm and
    back, rendered at 800×600. It rides a rotating empty and tracks the target, so its pose
    comes from a parent and a constraint, as users' camera rigs do. Every frame is a key, so the
    pose at each frame is known exactly whatever the keys' interpolation."""
    pivot = add_object(scene, "turntable pivot", None, target)
    aim = add_object(scene, "turntable target", None, target)
    data = bpy.data.cameras.new("turntable camera")
    data.sensor_width = 36.0
    camera = bpy.data.objects.new("turntable camera", data)
    camera.parent = pivot
    camera.location = (TURNTABLE_RADIUS, 0.0, TURNTABLE_HEIGHT)
    scene.collection.objects.link(camera)
    track = camera.constraints.new("TRACK_TO")
    track.target = aim
    track.track_axis = "TRACK_NEGATIVE_Z"
    track.up_axis = "UP_Y"
    for index in range(TURNTABLE_FRAMES):
        frame = 1 + index
        turn = 2.0 * math.pi * index / TURNTABLE_FRAMES
        pivot.rotation_euler = (0.0, 0.0, turn)
        pivot.keyframe_insert("rotation_euler", index=2, frame=frame)
        data.lens = 35.0 + 15.0 * (0.5 - 0.5 * math.cos(turn))
        data.keyframe_insert("lens", frame=frame)
    scene.camera = camera
    scene.frame_start, scene.frame_end = 1, TURNTABLE_FRAMES
    scene.frame_set(1)
    scene.render.fps, scene.render.fps_base = 24, 1.0
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 800, 600, 100
    return camera


def new_protocol_scene(name: str) -> "bpy.types.Scene":
    """A new, empty scene made for the protocol: a new scene's EEVEE, Filmic/AgX and opaque
    film would only be overridden."""
    scene = bpy.data.scenes.new(name)
    scene.render.engine = "CYCLES"
    scene.render.film_transparent = True
    scene.view_settings.view_transform = "Standard"
    return scene


def plain_world(name: str, colour: Sequence[float], strength: float) -> "bpy.types.World":
    """A uniform environment of one colour (`NAME world`): soft light from every direction
    (the film is transparent, so it is never seen directly)."""
    world = bpy.data.worlds.new(f"{name} world")
    tree = node_tree_of(world)
    background = next(node for node in tree.nodes if node.type == "BACKGROUND")
    background.inputs["Color"].default_value = (*colour, 1.0)
    background.inputs["Strength"].default_value = strength
    return world


def add_sun(scene: "bpy.types.Scene", name: str, energy: float, rotation_x_deg: float, rotation_z_deg: float,
            angle_deg: float = 5.0) -> "bpy.types.Object":
    """A sun light (`NAME sun`, object `sun`) for shadows: direction from the two rotations."""
    sun_data = bpy.data.lights.new(f"{name} sun", type="SUN")
    sun_data.energy = energy
    sun_data.angle = math.radians(angle_deg)
    return add_object(scene, "sun", sun_data, (0.0, 0.0, 3.0), rotation_x_deg=rotation_x_deg,
                      rotation_z_deg=rotation_z_deg)


def add_object(
    scene: "bpy.types.Scene",
    name: str,
    data: Optional["bpy.types.ID"],
    location: Sequence[float],
    rotation_x_deg: float = 0.0,
    rotation_z_deg: float = 0.0,
) -> "bpy.types.Object":
    obj = bpy.data.objects.new(name, data)
    obj.location = location
    obj.rotation_euler = Euler((math.radians(rotation_x_deg), 0.0, math.radians(rotation_z_deg)), "XYZ")
    scene.collection.objects.link(obj)
    return obj


def assign(obj: "bpy.types.Object", material: "bpy.types.Material") -> None:
    obj.data.materials.append(material)


def make_material(
    name: str, colour: Sequence[float], roughness: float, metallic: float = 0.0, diffuse: bool = False,
    transmission: float = 0.0, ior: Optional[float] = None,
) -> "bpy.types.Material":
    """A Principled material, or with `diffuse` a lone Diffuse BSDF of the same colour.
    `transmission` 1 with an `ior` makes glass."""
    material = bpy.data.materials.new(name)
    if diffuse:
        set_node_input(diffuse_bsdf(material), ["Color"], (*colour, 1.0))
        return material
    bsdf = principled_bsdf(material)
    set_node_input(bsdf, ["Base Color"], (*colour, 1.0))
    set_node_input(bsdf, ["Roughness"], roughness)
    set_node_input(bsdf, ["Metallic"], metallic)
    if transmission:
        set_node_input(bsdf, ["Transmission Weight", "Transmission"], transmission)
    if ior is not None:
        set_node_input(bsdf, ["IOR"], ior)
    return material


def textured_material(
    name: str,
    texture_node_type: str,
    colour_a: Sequence[float],
    colour_b: Sequence[float],
    scale: float,
    diffuse: bool = False,
) -> "bpy.types.Material":
    """A material whose base colour is a procedural texture on Generated coordinates."""
    material = make_material(name, colour_a, roughness=0.6, diffuse=diffuse)
    tree = node_tree_of(material)
    coordinates = tree.nodes.new("ShaderNodeTexCoord")
    texture = tree.nodes.new(texture_node_type)
    texture.inputs["Color1"].default_value = (*colour_a, 1.0)
    texture.inputs["Color2"].default_value = (*colour_b, 1.0)
    texture.inputs["Scale"].default_value = scale
    tree.links.new(coordinates.outputs["Generated"], texture.inputs["Vector"])
    shader = diffuse_bsdf(material) if diffuse else principled_bsdf(material)
    tree.links.new(texture.outputs["Color"], shader.inputs["Color" if diffuse else "Base Color"])
    return material


def mesh_from_bmesh(name: str, bm: "bmesh.types.BMesh", smooth: bool) -> "bpy.types.Mesh":
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    mesh.polygons.foreach_set("use_smooth", [smooth] * len(mesh.polygons))
    mesh.update()
    return mesh


def sphere_mesh(name: str, radius: float) -> "bpy.types.Mesh":
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=64, v_segments=32, radius=radius)
    return mesh_from_bmesh(name, bm, smooth=True)


def cube_mesh(name: str, size: float) -> "bpy.types.Mesh":
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=size)
    return mesh_from_bmesh(name, bm, smooth=False)


def cone_mesh(name: str, radius: float, height: float, segments: int) -> "bpy.types.Mesh":
    bm = bmesh.new()
    bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=segments,
                          radius1=radius, radius2=0.0, depth=height)
    return mesh_from_bmesh(name, bm, smooth=False)


def cylinder_mesh(name: str, radius: float, height: float, segments: int) -> "bpy.types.Mesh":
    """A capped cylinder centred on its origin, smooth sides and flat caps."""
    bm = bmesh.new()
    bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=segments,
                          radius1=radius, radius2=radius, depth=height)
    mesh = mesh_from_bmesh(name, bm, smooth=False)
    side = [abs(polygon.normal.z) < 0.5 for polygon in mesh.polygons]
    mesh.polygons.foreach_set("use_smooth", side)
    mesh.update()
    return mesh


def torus_mesh(name: str, major_radius: float, minor_radius: float,
               major_segments: int = 64, minor_segments: int = 16) -> "bpy.types.Mesh":
    """A torus in the XY plane around the origin (bmesh has no torus operator)."""
    vertices = []
    for i in range(major_segments):
        around = 2.0 * math.pi * i / major_segments
        for j in range(minor_segments):
            tube = 2.0 * math.pi * j / minor_segments
            distance = major_radius + minor_radius * math.cos(tube)
            vertices.append((distance * math.cos(around), distance * math.sin(around),
                             minor_radius * math.sin(tube)))
    faces = []
    for i in range(major_segments):
        next_i = (i + 1) % major_segments
        for j in range(minor_segments):
            next_j = (j + 1) % minor_segments
            faces.append((i * minor_segments + j, next_i * minor_segments + j,
                          next_i * minor_segments + next_j, i * minor_segments + next_j))
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices, [], faces)
    mesh.polygons.foreach_set("use_smooth", [True] * len(mesh.polygons))
    mesh.update()
    return mesh

