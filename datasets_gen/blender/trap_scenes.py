"""Trap scenes for the benchmark suite, built in code: each stands for a kind of user scene a
NeRF preset has failed on (the registry, with a line on each, is `builtin_scenes`).

They are fitted into the protocol's frame like any user scene (`--frame fit`); the sizes below
are Blender units, and each scene's bounding sphere is made about the fitted radius (1.229 for
the protocol camera) so that Blender units are about NeRF units, except `ground_plane`, whose
plane sets its scale.  At 100x100 the protocol camera sees 2.9 units across at the origin:
0.029 units a pixel.

* `bright_object`: a white sphere of radius 1.25 (after the fit about 1.2, about 60 % of every
  protocol frame) with a narrow dark groove (a thin torus, tilted so every view crosses it),
  under a white world and a sun: a large, bright object on the transparent film, where the
  blank white image already scores well and an empty model is a strong local minimum.
* `thin_structure`: a 3x3x3 lattice of wires of radius 0.018 (1.3 pixels wide at 100x100 at
  the centre, 1-2 pixels over the scene's depth), a thin ring (tube radius 0.012) on a rod
  (radius 0.015) above it, and a small solid sphere at the lattice's centre.
* `off_centre`: a cube with a ball on it filling one corner of the bounding box, a small cube
  in the opposite corner, nothing near the box's centre: the mass's centre is about 0.6 of the
  box's half-diagonal away from the box's centre.
* `ground_plane`: a 12x12 textured ground plane with four objects of about 1 unit on it: the
  plane sets the bounds (after the fit the objects are 5-8 pixels wide at 100x100).
* `glass_and_gloss`: a glass sphere and a glass cube (transmission 1, IOR 1.45), a chrome
  sphere and a copper torus (metallic, roughness 0.05 and 0.15) on a small diffuse base.

The material traps (issue 60), each with one kind of surface whose colour changes with the view:

* `glass_over_checker`: a clear glass sphere (radius 0.55, transmission 1, IOR 1.45) resting
  on a black-and-white checkerboard plate (a Diffuse BSDF): the board seen through the glass,
  refracted and flipped, moves with the view.
* `mirror_in_room` and `rough_in_room`: the same metal sphere and torus (metallic 1) on a
  diffuse base, under a world of coloured tiles (`room_world`: every reflection shows a
  pattern), roughness 0.03 (a mirror) and 0.45 (blurred reflections).
* `thin_film_coat`: a dark glossy sphere and torus coated with a thin film (450 and 300 nm, IOR
  1.33; Blender 4.2 and later): iridescent colours that shift with the view.
* `glass_dish`: a shallow dish of clear glass with a thin-film coat (walls 0.035 thick, 1.8
  across; IOR 1.5, film 400 nm), six glossy olives in it, under a uniform world: hollow glass, as
  the glTF sample IridescentDishWithOlives is, where what is seen through the walls is only
  shifted, and the glass's rims and silhouette show what Cycles' many bounces make of them.

Built with the demo's helpers (`demo_scene`), with the data API only; deterministic.
"""

from __future__ import annotations

import math
from typing import Sequence

import bmesh
import bpy
from mathutils import Matrix, Vector

from .compat import node_tree_of, principled_bsdf, set_node_input
from .demo_scene import (
    add_object,
    add_sun,
    assign,
    cone_mesh,
    cube_mesh,
    cylinder_mesh,
    make_material,
    mesh_from_bmesh,
    new_protocol_scene,
    plain_world,
    sphere_mesh,
    textured_material,
    torus_mesh,
)

SKY = (0.55, 0.60, 0.70)  # the demo's world colour


def _finish(scene: "bpy.types.Scene") -> "bpy.types.Scene":
    scene.view_layers[0].update()
    return scene


def build_bright_object(name: str = "NeRF bright_object") -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = plain_world(name, (1.0, 1.0, 1.0), 0.8)
    radius = 1.25
    sphere = add_object(scene, "white sphere", sphere_mesh("white sphere", radius), (0.0, 0.0, 0.0))
    assign(sphere, make_material("white", (0.9, 0.9, 0.9), roughness=0.5))
    groove = add_object(scene, "groove", torus_mesh("groove", radius, 0.03, major_segments=128),
                        (0.0, 0.0, 0.0), rotation_x_deg=25.0)
    assign(groove, make_material("groove", (0.03, 0.03, 0.03), roughness=0.6))
    add_sun(scene, name, energy=2.0, rotation_x_deg=35.0, rotation_z_deg=20.0)
    return _finish(scene)


def _wires_mesh(name: str, segments: Sequence[tuple[Sequence[float], Sequence[float]]],
                radius: float) -> "bpy.types.Mesh":
    """One mesh of thin capped cylinders, one between each pair of points."""
    bm = bmesh.new()
    for start, end in segments:
        a, b = Vector(start), Vector(end)
        axis = b - a
        rotation = axis.to_track_quat("Z", "Y").to_matrix().to_4x4()
        placement = Matrix.Translation((a + b) / 2.0) @ rotation
        bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=12, radius1=radius, radius2=radius,
                              depth=axis.length, matrix=placement)
    return mesh_from_bmesh(name, bm, smooth=True)


def build_thin_structure(name: str = "NeRF thin_structure") -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = plain_world(name, SKY, 0.6)
    half, wire = 0.55, 0.018
    levels = (-half, 0.0, half)
    reach = half + wire  # each wire runs past the corners by its radius, so the corners close
    segments = []
    for u in levels:
        for v in levels:
            segments.append(((-reach, u, v), (reach, u, v)))
            segments.append(((u, -reach, v), (u, reach, v)))
            segments.append(((u, v, -reach), (u, v, reach)))
    lattice = add_object(scene, "wire lattice", _wires_mesh("wire lattice", segments, wire), (0.0, 0.0, 0.0))
    assign(lattice, make_material("wire", (0.10, 0.20, 0.60), roughness=0.4))
    rod_length = 0.35
    rod = add_object(scene, "thin rod", cylinder_mesh("thin rod", 0.015, rod_length, 16),
                     (0.0, 0.0, half + rod_length / 2.0))
    assign(rod, make_material("rod", (0.60, 0.05, 0.05), roughness=0.4))
    ring_major = 0.17
    ring = add_object(scene, "thin ring", torus_mesh("thin ring", ring_major, 0.012),
                      (0.0, 0.0, half + rod_length + ring_major), rotation_x_deg=90.0, rotation_z_deg=30.0)
    assign(ring, make_material("ring", (0.10, 0.60, 0.25), roughness=0.3))
    core = add_object(scene, "solid sphere", sphere_mesh("solid sphere", 0.16), (0.0, 0.0, 0.0))
    assign(core, make_material("core", (0.90, 0.50, 0.10), roughness=0.5))
    add_sun(scene, name, energy=3.0, rotation_x_deg=40.0, rotation_z_deg=30.0)
    return _finish(scene)


def build_off_centre(name: str = "NeRF off_centre") -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = plain_world(name, SKY, 0.6)
    block = add_object(scene, "corner block", cube_mesh("corner block", 0.7), (-0.65, -0.65, -0.65))
    assign(block, textured_material("terracotta", "ShaderNodeTexChecker", (0.70, 0.30, 0.15), (0.85, 0.55, 0.35),
                                    scale=3.0))
    ball = add_object(scene, "corner ball", sphere_mesh("corner ball", 0.22), (-0.72, -0.72, -0.08))
    assign(ball, make_material("teal", (0.10, 0.50, 0.50), roughness=0.5))
    marker = add_object(scene, "far cube", cube_mesh("far cube", 0.12), (0.94, 0.94, 0.94))
    assign(marker, make_material("yellow", (0.90, 0.80, 0.10), roughness=0.5))
    add_sun(scene, name, energy=3.0, rotation_x_deg=40.0, rotation_z_deg=30.0)
    return _finish(scene)


def _plane_mesh(name: str, half: float) -> "bpy.types.Mesh":
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-half, -half, 0.0), (half, -half, 0.0), (half, half, 0.0), (-half, half, 0.0)], [],
                     [(0, 1, 2, 3)])
    mesh.update()
    return mesh


def build_ground_plane(name: str = "NeRF ground_plane") -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = plain_world(name, SKY, 0.6)
    ground = add_object(scene, "ground", _plane_mesh("ground", 6.0), (0.0, 0.0, 0.0))
    assign(ground, textured_material("ground", "ShaderNodeTexChecker", (0.45, 0.42, 0.38), (0.60, 0.57, 0.52),
                                     scale=12.0))
    cube = add_object(scene, "cube", cube_mesh("cube", 1.0), (-1.2, 0.6, 0.5), rotation_z_deg=20.0)
    assign(cube, make_material("blue", (0.10, 0.25, 0.70), roughness=0.6))
    ball = add_object(scene, "ball", sphere_mesh("ball", 0.6), (1.0, 0.9, 0.6))
    assign(ball, make_material("red", (0.75, 0.10, 0.08), roughness=0.4))
    cone = add_object(scene, "cone", cone_mesh("cone", 0.5, 1.2, 48), (0.2, -1.2, 0.6))
    assign(cone, make_material("green", (0.15, 0.55, 0.20), roughness=0.6))
    post = add_object(scene, "post", cylinder_mesh("post", 0.3, 1.6, 48), (1.6, -0.8, 0.8))
    assign(post, make_material("white", (0.85, 0.85, 0.80), roughness=0.5))
    add_sun(scene, name, energy=3.0, rotation_x_deg=40.0, rotation_z_deg=30.0)
    return _finish(scene)


def build_glass_and_gloss(name: str = "NeRF glass_and_gloss") -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = plain_world(name, SKY, 0.6)
    top = -0.5
    base = add_object(scene, "base", cylinder_mesh("base", 0.95, 0.14, 96), (0.0, 0.0, top - 0.07))
    assign(base, make_material("base", (0.50, 0.45, 0.40), roughness=1.0, diffuse=True))
    glass_ball = add_object(scene, "glass sphere", sphere_mesh("glass sphere", 0.33), (-0.4, -0.2, top + 0.33))
    assign(glass_ball, make_material("glass", (1.0, 1.0, 1.0), roughness=0.0, transmission=1.0, ior=1.45))
    glass_cube = add_object(scene, "glass cube", cube_mesh("glass cube", 0.4), (0.1, 0.45, top + 0.2),
                            rotation_z_deg=30.0)
    assign(glass_cube, make_material("green glass", (0.80, 0.95, 0.90), roughness=0.0, transmission=1.0, ior=1.45))
    chrome = add_object(scene, "chrome sphere", sphere_mesh("chrome sphere", 0.3), (0.45, -0.3, top + 0.3))
    assign(chrome, make_material("chrome", (0.90, 0.90, 0.90), roughness=0.05, metallic=1.0))
    ring = add_object(scene, "copper torus", torus_mesh("copper torus", 0.25, 0.07),
                      (-0.35, 0.45, top + 0.32), rotation_x_deg=90.0, rotation_z_deg=-30.0)
    assign(ring, make_material("copper", (0.95, 0.60, 0.45), roughness=0.15, metallic=1.0))
    add_sun(scene, name, energy=3.0, rotation_x_deg=40.0, rotation_z_deg=30.0)
    return _finish(scene)



def room_world(name: str) -> "bpy.types.World":
    """An environment of coloured tiles (a checker on the direction, `NAME world`): a polished
    surface reflects a pattern from every direction, as a textured room would, while the
    transparent film never shows it directly."""
    world = plain_world(name, (1.0, 1.0, 1.0), 1.0)
    tree = node_tree_of(world)
    coordinates = tree.nodes.new("ShaderNodeTexCoord")
    checker = tree.nodes.new("ShaderNodeTexChecker")
    checker.inputs["Color1"].default_value = (0.85, 0.55, 0.25, 1.0)
    checker.inputs["Color2"].default_value = (0.20, 0.35, 0.75, 1.0)
    checker.inputs["Scale"].default_value = 3.0
    tree.links.new(coordinates.outputs["Generated"], checker.inputs["Vector"])
    background = next(node for node in tree.nodes if node.type == "BACKGROUND")
    tree.links.new(checker.outputs["Color"], background.inputs["Color"])
    return world


def build_glass_over_checker(name: str = "NeRF glass_over_checker") -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = plain_world(name, SKY, 0.6)
    board = add_object(scene, "checkerboard", cube_mesh("checkerboard", 2.0), (0.0, 0.0, -0.55))
    board.scale = (1.0, 1.0, 0.04)
    assign(board, textured_material("checker", "ShaderNodeTexChecker", (0.9, 0.9, 0.9), (0.05, 0.05, 0.05), 8.0,
                                    diffuse=True))
    ball = add_object(scene, "glass sphere", sphere_mesh("glass sphere", 0.55), (0.0, 0.0, -0.51 + 0.55))
    assign(ball, make_material("glass", (1.0, 1.0, 1.0), roughness=0.0, transmission=1.0, ior=1.45))
    add_sun(scene, name, energy=3.0, rotation_x_deg=40.0, rotation_z_deg=30.0)
    return _finish(scene)


def _metal_in_room(name: str, roughness: float) -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = room_world(name)
    top = -0.45
    base = add_object(scene, "base", cylinder_mesh("base", 0.95, 0.14, 96), (0.0, 0.0, top - 0.07))
    assign(base, make_material("base", (0.50, 0.45, 0.40), roughness=1.0, diffuse=True))
    ball = add_object(scene, "metal sphere", sphere_mesh("metal sphere", 0.42), (-0.3, -0.15, top + 0.42))
    assign(ball, make_material("silver", (0.92, 0.92, 0.92), roughness=roughness, metallic=1.0))
    ring = add_object(scene, "metal torus", torus_mesh("metal torus", 0.28, 0.09), (0.4, 0.35, top + 0.37),
                      rotation_x_deg=90.0, rotation_z_deg=-30.0)
    assign(ring, make_material("gold", (0.95, 0.75, 0.40), roughness=roughness, metallic=1.0))
    return _finish(scene)


def build_mirror_in_room(name: str = "NeRF mirror_in_room") -> "bpy.types.Scene":
    return _metal_in_room(name, roughness=0.03)


def build_rough_in_room(name: str = "NeRF rough_in_room") -> "bpy.types.Scene":
    return _metal_in_room(name, roughness=0.45)


def _thin_film(name: str, colour: Sequence[float], thickness_nm: float) -> "bpy.types.Material":
    material = make_material(name, colour, roughness=0.08)
    bsdf = principled_bsdf(material)
    if "Thin Film Thickness" not in bsdf.inputs:
        raise RuntimeError(f"thin_film_coat needs the Principled BSDF's thin film (Blender 4.2 or later), "
                           f"not in Blender {bpy.app.version_string}")
    set_node_input(bsdf, ["Thin Film Thickness"], thickness_nm)
    set_node_input(bsdf, ["Thin Film IOR"], 1.33)
    return material


def build_thin_film_coat(name: str = "NeRF thin_film_coat") -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = plain_world(name, (0.9, 0.9, 0.9), 0.8)
    top = -0.45
    base = add_object(scene, "base", cylinder_mesh("base", 0.95, 0.14, 96), (0.0, 0.0, top - 0.07))
    assign(base, make_material("base", (0.50, 0.45, 0.40), roughness=1.0, diffuse=True))
    ball = add_object(scene, "coated sphere", sphere_mesh("coated sphere", 0.42), (-0.3, -0.15, top + 0.42))
    assign(ball, _thin_film("soap film", (0.04, 0.04, 0.05), 450.0))
    ring = add_object(scene, "coated torus", torus_mesh("coated torus", 0.28, 0.09), (0.4, 0.35, top + 0.37),
                      rotation_x_deg=90.0, rotation_z_deg=-30.0)
    assign(ring, _thin_film("oil film", (0.10, 0.08, 0.06), 300.0))
    add_sun(scene, name, energy=3.0, rotation_x_deg=40.0, rotation_z_deg=30.0)
    return _finish(scene)


def _dish_mesh(name: str, radius: float, height: float, wall: float, floor_radius: float) -> "bpy.types.Mesh":
    """A dish turned about z: a flat floor out to ``floor_radius``, then a wall curving up to
    ``radius`` at ``height``, ``wall`` thick everywhere, closed at the rim (one closed surface)."""
    steps = 10
    outer = [(0.0, 0.0), (floor_radius, 0.0)] + [
        (floor_radius + (radius - floor_radius) * math.sin(k / steps * math.pi / 2),
         height * (1.0 - math.cos(k / steps * math.pi / 2))) for k in range(1, steps + 1)]
    inner = [(max(r - wall, 0.0) if k > 1 else r, z + wall) for k, (r, z) in enumerate(outer)][::-1]
    inner[0] = (radius - wall, height)
    bm = bmesh.new()
    verts = [bm.verts.new((r, 0.0, z)) for r, z in outer + inner]
    edges = [bm.edges.new((verts[i], verts[i + 1])) for i in range(len(verts) - 1)]
    bmesh.ops.spin(bm, geom=verts + edges, cent=(0.0, 0.0, 0.0), axis=(0.0, 0.0, 1.0), angle=2.0 * math.pi,
                   steps=64, use_merge=True)
    bmesh.ops.remove_doubles(bm, verts=bm.verts, dist=1e-5)
    bmesh.ops.recalc_face_normals(bm, faces=bm.faces)
    return mesh_from_bmesh(name, bm, smooth=True)


def build_glass_dish(name: str = "NeRF glass_dish") -> "bpy.types.Scene":
    scene = new_protocol_scene(name)
    scene.world = plain_world(name, (0.9, 0.9, 0.9), 0.8)
    bottom = -0.35
    dish = add_object(scene, "glass dish", _dish_mesh("glass dish", 1.0, 0.3, 0.035, 0.55), (0.0, 0.0, bottom))
    glass = make_material("iridescent glass", (1.0, 1.0, 1.0), roughness=0.0, transmission=1.0, ior=1.5)
    if "Thin Film Thickness" not in principled_bsdf(glass).inputs:
        raise RuntimeError(f"glass_dish needs the Principled BSDF's thin film (Blender 4.2 or later), "
                           f"not in Blender {bpy.app.version_string}")
    set_node_input(principled_bsdf(glass), ["Thin Film Thickness"], 400.0)
    set_node_input(principled_bsdf(glass), ["Thin Film IOR"], 1.4)
    assign(dish, glass)
    olive = make_material("olive", (0.25, 0.30, 0.05), roughness=0.25)
    for index, (x, y, turn, lift) in enumerate([(-0.3, -0.1, 10.0, 0.0), (0.05, -0.3, 70.0, 0.0),
                                                (0.3, 0.05, 130.0, 0.0), (-0.05, 0.25, 40.0, 0.0),
                                                (-0.35, 0.3, 100.0, 0.0), (0.1, 0.0, 160.0, 0.1)]):
        mesh = sphere_mesh(f"olive {index}", 0.14)
        mesh.transform(Matrix.Diagonal((1.0, 0.72, 0.72, 1.0)))
        assign(add_object(scene, f"olive {index}", mesh, (x, y, bottom + 0.035 + 0.10 + lift), rotation_z_deg=turn),
               olive)
    add_sun(scene, name, energy=3.0, rotation_x_deg=40.0, rotation_z_deg=30.0)
    return _finish(scene)
