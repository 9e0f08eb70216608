"""Build the generator's test scenes in code and save them as .blend files.

Run as `python make_scenes.py OUT_DIR [NAME ...]` with a Python that has the bpy module (all
scenes without NAMEs; a NAME is a file name below without ".blend", e.g. "sphere").  Each scene stands
for a kind of real-world file the generator must handle (see tests/test_datasets_gen_scenes.py):

    missing_texture.blend   a cube whose Image Texture points at //textures/brick_diffuse.png (absent)
    missing_library.blend   a local cube plus an object linked from //library.blend, which is deleted
    empty_only.blend        an Empty and a light: nothing to render
    all_hidden.blend        meshes hidden from render (object flag, render-disabled collection)
    unit.blend, tiny.blend, huge.blend, far.blend, far_huge.blend
                            the same object placed and scaled as PLACEMENTS says (issue 7's extremes:
                            scale 1e-3, scale 1e4, 1e5 units from the origin, and scale 1e4 far away)
    eevee_filmic.blend      EEVEE, Filmic with exposure and gamma, opaque film, stamps, two view layers,
                            a render-hidden helper far away, a viewport-hidden object that renders,
                            an excluded collection instanced by an Empty
    markers.blend           three small emissive spheres (red, green, blue) at MARKERS
    sphere.blend            a fine smooth-shaded UV sphere of radius 2 at (3, -2, 1)
    occupancy.blend         what the occupancy prior must see beyond plain meshes: a cube subdivided
                            only for render (viewport level 0), a ball with particle hair, a ball
                            with true displacement, one whose displacement scale is linked (unreadable),
                            and hair curves (a CURVES object, which to_mesh cannot measure)
    materials.blend         a row of spheres, each of one material the scene profile's facts must read:
                            glass, metal whose roughness a Noise Texture drives (through a reroute),
                            a thin-film coat, a Principled BSDF inside a node group whose roughness is
                            the group's input, a Principled BSDF mixed with a Glossy BSDF, and a plain
                            diffuse one
"""

from __future__ import annotations

import json
import math
import os
import sys

import bpy
import bmesh  # after bpy: the bpy module provides it

MARKERS = [[0.0, 0.0, 0.0], [0.3, 0.35, 0.3], [-0.3, -0.3, -0.25]]
MARKER_RADIUS = 0.03
SPHERE_CENTRE = (3.0, -2.0, 1.0)
SPHERE_RADIUS = 2.0
#: name -> (location, uniform scale) of the Empty that places the same object (see placed_object).
#: "far" is 1e5 units from the origin (a unit vector (2, -2, 1) / 3 times 1e5) at scale 1, where
#: Blender's float32 step is 2**-7 = 0.0078 units, 0.3 % of the object's bounding sphere (diameter 2.7).
PLACEMENTS = {
    "unit": ((0.0, 0.0, 0.0), 1.0),
    "tiny": ((0.0, 0.0, 0.0), 1.0e-3),
    "huge": ((0.0, 0.0, 0.0), 1.0e4),
    "far": ((2.0e5 / 3.0, -2.0e5 / 3.0, 1.0e5 / 3.0), 1.0),
    "far_huge": ((1.0e5, -2.0e5, 3.0e4), 1.0e4),
}


def reset() -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    return scene


def save(out_dir: str, name: str) -> None:
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(out_dir, name), check_existing=False)


def mesh_object(scene, name: str, kind: str, size: float = 1.0, location=(0.0, 0.0, 0.0),
                collection=None) -> bpy.types.Object:
    bm = bmesh.new()
    if kind == "cube":
        bmesh.ops.create_cube(bm, size=size)
    elif kind == "sphere":
        bmesh.ops.create_uvsphere(bm, u_segments=128, v_segments=64, radius=size)
    elif kind == "small_sphere":
        bmesh.ops.create_uvsphere(bm, u_segments=16, v_segments=8, radius=size)
    elif kind == "cone":
        bmesh.ops.create_cone(bm, cap_ends=True, cap_tris=False, segments=32, radius1=size, radius2=0.0,
                              depth=2 * size)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    (collection or scene.collection).objects.link(obj)
    return obj


def material(name: str, colour, emission: bool = False) -> bpy.types.Material:
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    for node in list(nodes):
        if node.type != "OUTPUT_MATERIAL":
            nodes.remove(node)
    shader = nodes.new("ShaderNodeEmission" if emission else "ShaderNodeBsdfDiffuse")
    shader.inputs["Color"].default_value = (*colour, 1.0)
    output = next(n for n in nodes if n.type == "OUTPUT_MATERIAL")
    mat.node_tree.links.new(shader.outputs[0], output.inputs["Surface"])
    return mat


def world(scene, colour=(0.6, 0.6, 0.6)) -> None:
    w = bpy.data.worlds.new("world")
    if w.node_tree is None:
        w.use_nodes = True
    w.node_tree.nodes["Background"].inputs["Color"].default_value = (*colour, 1.0)
    scene.world = w


def sun(scene) -> None:
    light = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    light.data.energy = 3.0
    light.rotation_euler = (math.radians(40), 0.0, math.radians(30))
    scene.collection.objects.link(light)


def missing_texture(out_dir: str) -> None:
    scene = reset()
    world(scene)
    cube = mesh_object(scene, "Textured cube", "cube")
    mat = material("brick", (0.8, 0.3, 0.2))
    image = bpy.data.images.new("brick_diffuse.png", 4, 4)
    image.source = "FILE"
    image.filepath = "//textures/brick_diffuse.png"
    texture = mat.node_tree.nodes.new("ShaderNodeTexImage")
    texture.image = image
    shader = next(n for n in mat.node_tree.nodes if n.type == "BSDF_DIFFUSE")
    mat.node_tree.links.new(texture.outputs["Color"], shader.inputs["Color"])
    cube.data.materials.append(mat)
    save(out_dir, "missing_texture.blend")


def missing_library(out_dir: str) -> None:
    scene = reset()
    mesh_object(scene, "LibraryCube", "cube")
    library = os.path.join(out_dir, "library.blend")
    save(out_dir, "library.blend")
    scene = reset()
    world(scene)
    mesh_object(scene, "Local cube", "cube")
    with bpy.data.libraries.load(library, link=True, relative=True) as (_source, target):
        target.objects = ["LibraryCube"]
    for obj in target.objects:
        scene.collection.objects.link(obj)
    save(out_dir, "missing_library.blend")
    os.remove(library)


def empty_only(out_dir: str) -> None:
    scene = reset()
    empty = bpy.data.objects.new("Just an Empty", None)
    scene.collection.objects.link(empty)
    sun(scene)
    save(out_dir, "empty_only.blend")


def all_hidden(out_dir: str) -> None:
    scene = reset()
    hidden = mesh_object(scene, "Hidden cube", "cube")
    hidden.hide_render = True
    collection = bpy.data.collections.new("Render-disabled")
    collection.hide_render = True
    scene.collection.children.link(collection)
    mesh_object(scene, "Cube in a hidden collection", "cube", collection=collection)
    scene.collection.objects.link(bpy.data.objects.new("Rig helper", None))
    save(out_dir, "all_hidden.blend")


def placed_object(out_dir: str, name: str, offset, scale: float) -> None:
    """An asymmetric object (cube, sphere, cone) under an Empty that places and scales it.

    The lighting is scale- and place-invariant, so every placement renders the same image from
    the same relative viewpoint: a uniform world background and a sun (direction only: W/m^2, no
    fall-off).  A point or area light would not do: its irradiance falls off with distance squared,
    so the object 1e4 times larger would need its light 1e8 times stronger.
    """
    scene = reset()
    world(scene)
    sun(scene)
    rig = bpy.data.objects.new("placement", None)
    rig.location = offset
    rig.scale = (scale, scale, scale)
    scene.collection.objects.link(rig)
    parts = [
        ("cube", "cube", 1.0, (0.0, 0.0, 0.0), (0.8, 0.2, 0.2)),
        ("ball", "small_sphere", 0.4, (0.9, 0.0, 0.1), (0.2, 0.7, 0.2)),
        ("cone", "cone", 0.3, (0.0, 0.8, 0.5), (0.2, 0.3, 0.9)),
    ]
    for part, kind, size, location, colour in parts:
        obj = mesh_object(scene, part, kind, size, location)
        obj.parent = rig
        obj.data.materials.append(material(part, colour))
    save(out_dir, name)


def eevee_filmic(out_dir: str) -> None:
    scene = reset()
    world(scene, (0.3, 0.35, 0.4))
    sun(scene)
    engines = {item.identifier for item in bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items}
    scene.render.engine = "BLENDER_EEVEE_NEXT" if "BLENDER_EEVEE_NEXT" in engines else "BLENDER_EEVEE"
    scene.view_settings.view_transform = "Filmic"
    scene.view_settings.exposure = 0.5
    scene.view_settings.gamma = 1.2
    scene.render.film_transparent = False
    scene.render.use_stamp = True
    scene.render.resolution_x, scene.render.resolution_y = 1280, 720
    scene.render.resolution_percentage = 5  # 64 x 36 with --use-scene-camera
    scene.view_layers.new("Second layer")
    cube = mesh_object(scene, "Cube", "cube", 1.0, (0.0, 0.0, 0.0))
    cube.data.materials.append(material("red", (0.8, 0.1, 0.1)))
    helper = mesh_object(scene, "Helper plane", "cube", 50.0, (0.0, 0.0, -40.0))
    helper.hide_render = True
    viewport_hidden = mesh_object(scene, "Viewport-hidden ball", "small_sphere", 0.5, (2.0, 0.0, 0.0))
    viewport_hidden.hide_viewport = True
    # An excluded "Assets" collection, instanced by an Empty: the instance renders, the source does not.
    assets = bpy.data.collections.new("Assets")
    scene.collection.children.link(assets)
    mesh_object(scene, "Asset cube", "cube", 1.0, (0.0, 0.0, 10.0), collection=assets)
    assets.instance_offset = (0.0, 0.0, 10.0)
    for layer in scene.view_layers:
        layer.layer_collection.children["Assets"].exclude = True
    instancer = bpy.data.objects.new("Asset instance", None)
    instancer.instance_type = "COLLECTION"
    instancer.instance_collection = assets
    instancer.location = (-2.0, 0.0, 0.0)
    scene.collection.objects.link(instancer)
    camera = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    camera.location = (0.0, -8.0, 1.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    save(out_dir, "eevee_filmic.blend")


def markers(out_dir: str) -> None:
    scene = reset()
    for index, location in enumerate(MARKERS):
        colour = [0.0, 0.0, 0.0]
        colour[index] = 1.0
        obj = mesh_object(scene, f"marker{index}", "small_sphere", MARKER_RADIUS, tuple(location))
        obj.data.materials.append(material(f"emit{index}", colour, emission=True))
    save(out_dir, "markers.blend")


def sphere(out_dir: str) -> None:
    scene = reset()
    world(scene)
    sun(scene)
    obj = mesh_object(scene, "Sphere", "sphere", SPHERE_RADIUS, SPHERE_CENTRE)
    obj.data.polygons.foreach_set("use_smooth", [True] * len(obj.data.polygons))
    obj.data.update()
    obj.data.materials.append(material("grey", (0.7, 0.7, 0.7)))
    save(out_dir, "sphere.blend")


def flat(out_dir: str) -> None:
    """A single square plane at z = 0: a scene with no extent along one axis."""
    scene = reset()
    world(scene)
    sun(scene)
    bm = bmesh.new()
    bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=1.0)
    mesh = bpy.data.meshes.new("Card")
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new("Card", mesh)
    scene.collection.objects.link(obj)
    obj.data.materials.append(material("card", (0.8, 0.3, 0.2)))
    save(out_dir, "flat.blend")


def occupancy(out_dir: str) -> None:
    scene = reset()
    world(scene)
    sun(scene)
    grey = material("grey", (0.7, 0.7, 0.7))
    cage = mesh_object(scene, "Subdivided cage", "cube", 2.0)
    cage.data.materials.append(grey)
    subdivision = cage.modifiers.new("Subdivision", "SUBSURF")
    subdivision.levels, subdivision.render_levels = 0, 3  # the render shrinks well inside the cage
    hairy = mesh_object(scene, "Hairy", "small_sphere", 0.4, (2.5, 0.0, 0.0))
    hairy.data.materials.append(grey)
    hairy.modifiers.new("Fur", "PARTICLE_SYSTEM")
    fur = hairy.particle_systems[0].settings
    fur.type, fur.count, fur.hair_length = "HAIR", 50, 0.5
    displaced = mesh_object(scene, "Displaced", "small_sphere", 0.4, (-2.5, 0.0, 0.0))
    displaced.data.materials.append(displacing_material("bumpy", linked_scale=False))
    unreadable = mesh_object(scene, "Unreadable", "small_sphere", 0.3, (0.0, 2.5, 0.0))
    unreadable.data.materials.append(displacing_material("unreadable", linked_scale=True))
    curves = bpy.data.hair_curves.new("Strands")
    curves.add_curves([2, 2, 2])
    for index, point in enumerate(curves.points):
        point.position = (0.1 * (index // 2), 0.0, float(index % 2))
        point.radius = 0.01
    strands = bpy.data.objects.new("Strands", curves)
    strands.location = (0.0, -2.5, -0.5)
    scene.collection.objects.link(strands)
    save(out_dir, "occupancy.blend")


def displacing_material(name: str, linked_scale: bool) -> bpy.types.Material:
    """Cycles true displacement by a noise texture; its Displacement node's Scale 0.3, or linked."""
    mat = material(name, (0.6, 0.5, 0.4))
    mat.displacement_method = "DISPLACEMENT"
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    displacement = nodes.new("ShaderNodeDisplacement")
    displacement.inputs["Scale"].default_value = 0.3
    noise = nodes.new("ShaderNodeTexNoise")
    links.new(noise.outputs["Fac"], displacement.inputs["Height"])
    if linked_scale:
        links.new(nodes.new("ShaderNodeValue").outputs[0], displacement.inputs["Scale"])
    output = next(n for n in nodes if n.type == "OUTPUT_MATERIAL")
    links.new(displacement.outputs[0], output.inputs["Displacement"])
    return mat


def principled_material(name: str, **inputs) -> tuple[bpy.types.Material, bpy.types.Node]:
    """A material of one Principled BSDF with ``inputs`` (socket name with spaces as _) set."""
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:
        mat.use_nodes = True
    nodes = mat.node_tree.nodes
    shader = next(n for n in nodes if n.type == "BSDF_PRINCIPLED")
    for key, value in inputs.items():
        shader.inputs[key.replace("_", " ")].default_value = value
    return mat, shader


def materials(out_dir: str) -> None:
    scene = reset()
    world(scene)
    sun(scene)
    made = []
    made.append(principled_material("Glass", Transmission_Weight=1.0, Roughness=0.0, IOR=1.5)[0])
    metal, shader = principled_material("Metal", Metallic=1.0)
    noise = metal.node_tree.nodes.new("ShaderNodeTexNoise")
    noise.name = "Scratches"
    reroute = metal.node_tree.nodes.new("NodeReroute")
    metal.node_tree.links.new(noise.outputs["Fac"], reroute.inputs[0])
    metal.node_tree.links.new(reroute.outputs[0], shader.inputs["Roughness"])
    made.append(metal)
    made.append(principled_material("Film", Roughness=0.1, Thin_Film_Thickness=500.0, Thin_Film_IOR=1.33)[0])
    grouped = bpy.data.materials.new("Grouped")
    if grouped.node_tree is None:
        grouped.use_nodes = True
    for node in list(grouped.node_tree.nodes):
        if node.type != "OUTPUT_MATERIAL":
            grouped.node_tree.nodes.remove(node)
    group = bpy.data.node_groups.new("Coated", "ShaderNodeTree")
    group.interface.new_socket("Roughness", in_out="INPUT", socket_type="NodeSocketFloat")
    group.interface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    inside = group.nodes.new("ShaderNodeBsdfPrincipled")
    inside.inputs["Coat Weight"].default_value = 0.8
    group.links.new(group.nodes.new("NodeGroupInput").outputs["Roughness"], inside.inputs["Roughness"])
    group.links.new(inside.outputs[0], group.nodes.new("NodeGroupOutput").inputs["Shader"])
    instance = grouped.node_tree.nodes.new("ShaderNodeGroup")
    instance.node_tree = group
    instance.inputs["Roughness"].default_value = 0.3
    output = next(n for n in grouped.node_tree.nodes if n.type == "OUTPUT_MATERIAL")
    grouped.node_tree.links.new(instance.outputs[0], output.inputs["Surface"])
    made.append(grouped)
    mixed, shader = principled_material("Mixed", Roughness=0.2)
    nodes, links = mixed.node_tree.nodes, mixed.node_tree.links
    glossy, mix = nodes.new("ShaderNodeBsdfGlossy"), nodes.new("ShaderNodeMixShader")
    glossy.name = "Sheen layer"
    links.new(shader.outputs[0], mix.inputs[1])
    links.new(glossy.outputs[0], mix.inputs[2])
    links.new(mix.outputs[0], next(n for n in nodes if n.type == "OUTPUT_MATERIAL").inputs["Surface"])
    made.append(mixed)
    made.append(material("Chalk", (0.8, 0.8, 0.8)))
    for index, mat in enumerate(made):
        obj = mesh_object(scene, mat.name + "Ball", "small_sphere", 0.4, (1.0 * index - 2.5, 0.0, 0.0))
        obj.data.materials.append(mat)
    save(out_dir, "materials.blend")


BUILDERS = {
    "missing_texture": missing_texture,
    "missing_library": missing_library,
    "empty_only": empty_only,
    "all_hidden": all_hidden,
    **{name: (lambda out_dir, name=name: placed_object(out_dir, f"{name}.blend", *PLACEMENTS[name]))
       for name in PLACEMENTS},
    "eevee_filmic": eevee_filmic,
    "markers": markers,
    "sphere": sphere,
    "flat": flat,
    "occupancy": occupancy,
    "materials": materials,
}


def main() -> None:
    arguments = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    out_dir, names = arguments[0], arguments[1:] or list(BUILDERS)
    os.makedirs(out_dir, exist_ok=True)
    for name in names:
        BUILDERS[name](out_dir)
    with open(os.path.join(out_dir, "scenes.json"), "w") as handle:
        json.dump({"markers": MARKERS, "sphere_centre": SPHERE_CENTRE, "sphere_radius": SPHERE_RADIUS,
                   "placements": {name: {"offset": offset, "scale": scale}
                                  for name, (offset, scale) in PLACEMENTS.items()}}, handle)


if __name__ == "__main__":
    main()
