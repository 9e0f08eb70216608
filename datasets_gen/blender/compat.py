"""The few Blender API differences between 3.4 (Debian's binary) and 5.x (the bpy module).

Each helper tries the newer spelling and falls back to the older one, so the rest of the code
reads as if there were a single Blender.
"""

from __future__ import annotations

from typing import Any, Sequence

import bpy


def set_eevee(scene: "bpy.types.Scene", journal: Any) -> None:
    """Make EEVEE the scene's engine: ``BLENDER_EEVEE`` (5.x, and before 4.2), ``BLENDER_EEVEE_NEXT``
    (4.2-4.5)."""
    try:
        journal.set(scene.render, "engine", "BLENDER_EEVEE")
    except TypeError:
        journal.set(scene.render, "engine", "BLENDER_EEVEE_NEXT")


def node_tree_of(block: Any) -> "bpy.types.NodeTree":
    """The shader node tree of a material or world, creating it where Blender < 5 needs `use_nodes`.

    Blender 5 always has a tree and deprecates `use_nodes`, so it is only touched when needed.
    """
    if block.node_tree is None:
        block.use_nodes = True
    return block.node_tree


def principled_bsdf(material: "bpy.types.Material") -> "bpy.types.Node":
    """The Principled BSDF node of a new material (both versions create one)."""
    tree = node_tree_of(material)
    for node in tree.nodes:
        if node.type == "BSDF_PRINCIPLED":
            return node
    node = tree.nodes.new("ShaderNodeBsdfPrincipled")
    output = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
    tree.links.new(node.outputs[0], output.inputs["Surface"])
    return node


def diffuse_bsdf(material: "bpy.types.Material") -> "bpy.types.Node":
    """The material's Diffuse BSDF, made its only shader (any Principled BSDF is removed)."""
    tree = node_tree_of(material)
    for node in tree.nodes:
        if node.type == "BSDF_DIFFUSE":
            return node
    for node in list(tree.nodes):
        if node.type == "BSDF_PRINCIPLED":
            tree.nodes.remove(node)
    node = tree.nodes.new("ShaderNodeBsdfDiffuse")
    output = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
    tree.links.new(node.outputs[0], output.inputs["Surface"])
    return node


def node_input(node: "bpy.types.Node", names: Sequence[str]) -> "bpy.types.NodeSocket":
    """The first of `names` the node has: socket names changed in 4.0 ("Specular" -> "Specular IOR Level")."""
    for name in names:
        socket = node.inputs.get(name)
        if socket is not None:
            return socket
    raise KeyError(f"node {node.name!r} has none of the inputs {list(names)}")


def set_node_input(node: "bpy.types.Node", names: Sequence[str], value: Any) -> None:
    """Set the default value of the first existing input among `names`."""
    node_input(node, names).default_value = value
