"""Results brought into the scene as objects: the NeRF's mesh (a PLY with vertex colours) and
its baked asset (glTF binary), both in Blender's world already (the backend undid the dataset's
``world_to_nerf``)."""

from __future__ import annotations

from pathlib import Path

import bpy

from datasets_gen.blender.compat import node_tree_of

MESH_OBJECT, MESH_MATERIAL = "NeRF mesh", "NeRF mesh vertex colours"
ASSET_OBJECT = "NeRF asset"


def _new_objects(load) -> list:
    """The objects ``load()`` adds to the file."""
    before = set(bpy.data.objects)
    load()
    return [obj for obj in bpy.data.objects if obj not in before]


def import_mesh(context, path: Path):
    """The PLY as a new object (in Blender's world already: the backend undid world_to_nerf)
    with a material showing its vertex colours."""
    new = _new_objects(lambda: bpy.ops.wm.ply_import(filepath=str(path)))
    if len(new) != 1:
        raise RuntimeError(f"{path}: the PLY importer made {len(new)} objects")
    obj = new[0]
    obj.name = MESH_OBJECT
    attributes = getattr(obj.data, "color_attributes", None)
    colour = attributes[0].name if attributes else "Col"
    obj.data.materials.clear()
    obj.data.materials.append(_vertex_colour_material(colour))
    return obj


def _vertex_colour_material(attribute: str):
    material = bpy.data.materials.get(MESH_MATERIAL) or bpy.data.materials.new(MESH_MATERIAL)
    tree = node_tree_of(material)
    tree.nodes.clear()
    colour = tree.nodes.new("ShaderNodeVertexColor")
    colour.layer_name = attribute
    emission = tree.nodes.new("ShaderNodeEmission")  # the NeRF's colours already hold the scene's lighting
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    tree.links.new(colour.outputs["Color"], emission.inputs["Color"])
    tree.links.new(emission.outputs["Emission"], output.inputs["Surface"])
    return material


def import_asset(context, path: Path):
    """The glTF asset as a new object named ``ASSET_OBJECT``, with the material it carries (the
    baked texture, unlit: Blender's importer makes it an emission shader seen by the camera)."""
    new = _new_objects(lambda: bpy.ops.import_scene.gltf(filepath=str(path)))
    meshes = [obj for obj in new if obj.type == "MESH"]
    if len(meshes) != 1:
        raise RuntimeError(f"{path}: the glTF importer made {len(meshes)} mesh objects, not one")
    meshes[0].name = ASSET_OBJECT
    return meshes[0]
