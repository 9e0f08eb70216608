"""Facts about a scene, read from Blender into plain data for the pure checks and the profile.

Nothing here decides anything: `scene_checks.evaluate` and `materials.classify_material` do,
on the plain values collected here (the split the glTF add-on uses between its Blender
reading and its export logic).
"""

from __future__ import annotations

import hashlib
import os
from typing import Any, Iterable, Optional

import bpy

from nerf_contract.dataset_layout import WORLD_UNIFORM

from ..core.materials import choose_output_node
from ..core.scene_checks import MissingFile

FILE_IMAGE_SOURCES = {"FILE", "SEQUENCE", "MOVIE", "TILED"}
_SCALAR_SOCKETS = {"VALUE", "INT", "BOOLEAN"}


# --- external files ----------------------------------------------------------------------


def _absolute(path: str, library: Optional["bpy.types.Library"] = None) -> str:
    return os.path.normpath(bpy.path.abspath(path, library=library))


def _exists(path: str) -> bool:
    """Whether a file exists, also trying a Windows-style path with '/' separators."""
    return os.path.exists(path) or os.path.exists(path.replace("\\", "/"))


def _in_use(block: "bpy.types.ID") -> bool:
    """Used by something other than a fake user."""
    return block.users - int(bool(getattr(block, "use_fake_user", False))) > 0


def _users(block: "bpy.types.ID", user_map: dict) -> list[str]:
    names = sorted(f"{type(user).__name__.lower()} {user.name!r}" for user in user_map.get(block, ()))
    return names[:5] + ([f"{len(names) - 5} more"] if len(names) > 5 else [])


def _image_files(image: "bpy.types.Image") -> list[str]:
    """The files an image reads (one per UDIM tile for tiled images)."""
    path = _absolute(image.filepath, image.library)
    if image.source == "TILED" and "<UDIM>" in path:
        return [path.replace("<UDIM>", str(tile.number)) for tile in image.tiles]
    return [path]


def missing_files() -> list[MissingFile]:
    """Images, linked libraries, volumes, caches and fonts the file refers to but are not on disk."""
    found: list[MissingFile] = []
    user_map = bpy.data.user_map()
    for library in bpy.data.libraries:
        path = _absolute(library.filepath, getattr(library, "parent", None))
        if not _exists(path):
            linked = [f"{type(block).__name__.lower()} {block.name!r}"
                      for block in _linked_blocks(library)]
            found.append(MissingFile("library", path, library.name, tuple(linked[:5]), library.filepath))
    for image in bpy.data.images:
        if image.source not in FILE_IMAGE_SOURCES or not _in_use(image) or image.packed_file is not None:
            continue
        for path in _image_files(image):
            if not _exists(path):
                found.append(MissingFile("image", path, image.name, tuple(_users(image, user_map)), image.filepath))
    for kind, blocks in (("volume", bpy.data.volumes), ("cache file", bpy.data.cache_files),
                         ("font", bpy.data.fonts)):
        for block in blocks:
            filepath = getattr(block, "filepath", "")
            if (not filepath or filepath == "<builtin>" or not _in_use(block)
                    or getattr(block, "packed_file", None) is not None):
                continue
            path = _absolute(filepath, block.library)
            if not _exists(path):
                found.append(MissingFile(kind, path, block.name, tuple(_users(block, user_map)), filepath))
    return found


def _linked_blocks(library: "bpy.types.Library") -> Iterable["bpy.types.ID"]:
    for collection in (bpy.data.objects, bpy.data.collections, bpy.data.meshes, bpy.data.materials,
                       bpy.data.node_groups, bpy.data.worlds, bpy.data.images):
        for block in collection:
            if block.library == library:
                yield block


# --- materials and world -----------------------------------------------------------------


def _socket_value(socket: "bpy.types.NodeSocket") -> Any:
    """A number, a colour's [r, g, b], or None (a shader, a vector)."""
    if socket.type in _SCALAR_SOCKETS and hasattr(socket, "default_value"):
        return float(socket.default_value)
    if socket.type == "RGBA" and hasattr(socket, "default_value"):
        return [float(channel) for channel in socket.default_value[:3]]
    return None


def _link_source(socket: "bpy.types.NodeSocket") -> Optional[dict]:
    """The node a linked input's value comes from (through reroutes), named as Blender shows it."""
    links = [link for link in socket.links if link.is_valid and not getattr(link, "is_muted", False)]
    if not links:
        return None
    node = links[0].from_node
    while node.type == "REROUTE" and node.inputs and node.inputs[0].links:
        node = node.inputs[0].links[0].from_node
    return {"type": node.type, "name": node.name, "label": node.bl_label}


def _describe_input(socket: "bpy.types.NodeSocket") -> dict:
    described = {"value": _socket_value(socket), "linked": bool(socket.is_linked)}
    if socket.is_linked and (source := _link_source(socket)) is not None:
        described["from"] = source
    return described


def _describe_node(node: "bpy.types.Node") -> dict:
    return {
        "name": node.name,
        "type": node.type,
        "inputs": {socket.name: _describe_input(socket) for socket in node.inputs},
        "linked_outputs": [socket.name for socket in node.outputs if socket.is_linked],
    }


def _reachable(tree: "bpy.types.NodeTree", roots: list, seen: set, out: list) -> None:
    """Describe every node that feeds `roots` (through groups, reroutes and muted nodes)."""
    stack = list(roots)
    while stack:
        node = stack.pop()
        key = (tree.as_pointer(), node.name)
        if key in seen:
            continue
        seen.add(key)
        if node.type == "GROUP" and node.node_tree is not None and not node.mute:
            inner = [n for n in node.node_tree.nodes if n.type == "GROUP_OUTPUT"]
            _reachable(node.node_tree, inner, seen, out)
        elif node.type not in ("REROUTE", "GROUP_INPUT", "GROUP_OUTPUT", "FRAME") and not node.mute:
            out.append(_describe_node(node))
        for socket in node.inputs:
            for link in socket.links:
                if link.is_valid and not getattr(link, "is_muted", False):
                    stack.append(link.from_node)


def _cycles_output(tree: "bpy.types.NodeTree", node_type: str) -> Optional["bpy.types.Node"]:
    outputs = [node for node in tree.nodes if node.type == node_type]
    index = choose_output_node(
        [{"target": getattr(node, "target", "ALL"), "is_active_output": getattr(node, "is_active_output", False)}
         for node in outputs]
    )
    return None if index is None else outputs[index]


def _shader_nodes(block: "bpy.types.ID", output_type: str, inputs: tuple[str, ...]) -> Optional[list[dict]]:
    """Descriptions of the nodes Cycles evaluates for a material or world (None: no node tree)."""
    tree = getattr(block, "node_tree", None)
    if tree is None or not getattr(block, "use_nodes", True):
        return None
    output = _cycles_output(tree, output_type)
    if output is None:
        return []
    roots = [link.from_node for name in inputs if name in output.inputs for link in output.inputs[name].links]
    described: list[dict] = []
    _reachable(tree, roots, set(), described)
    return described


def describe_material(name: str, objects: list[str]) -> dict:
    """The classifier's input for one material (see materials.classify_material)."""
    material = bpy.data.materials.get(name)
    nodes = _shader_nodes(material, "OUTPUT_MATERIAL", ("Surface", "Volume")) if material else None
    return {"name": name, "objects": objects, "uses_nodes": nodes is not None, "nodes": nodes or []}


def describe_world(scene: "bpy.types.Scene") -> dict:
    """What lights the scene from around: a uniform colour, an environment image, a sky, or nodes."""
    world = scene.world
    if world is None:
        return {"name": None, "kind": "none (black)"}
    nodes = _shader_nodes(world, "OUTPUT_WORLD", ("Surface", "Volume"))
    if nodes is None:
        return {"name": world.name, "kind": WORLD_UNIFORM, "color": [float(c) for c in world.color]}
    types = sorted({node["type"] for node in nodes})
    record: dict[str, Any] = {"name": world.name, "node_types": types}
    images = []
    tree = world.node_tree
    for node in tree.nodes:
        if node.type == "TEX_ENVIRONMENT" and node.image is not None:
            images.append(node.image.name)
    if "TEX_ENVIRONMENT" in types:
        record["kind"] = "environment image"
        record["images"] = sorted(images)
    elif "TEX_SKY" in types:
        record["kind"] = "sky texture"
    elif types == ["BACKGROUND"] and not any(socket["linked"] for node in nodes for socket in node["inputs"].values()):
        record["kind"] = WORLD_UNIFORM
        background = next(node for node in tree.nodes if node.type == "BACKGROUND")
        record["color"] = [float(c) for c in background.inputs["Color"].default_value]
        record["strength"] = float(background.inputs["Strength"].default_value)
    else:
        record["kind"] = "node tree" if types else "none (black)"
    return record


def texture_records() -> list[dict]:
    """Every image in use: where it comes from, its size in pixels, whether its file is missing."""
    records = []
    for image in bpy.data.images:
        if image.source in ("VIEWER",) or not _in_use(image):
            continue
        record: dict[str, Any] = {"name": image.name, "source": image.source,
                                  "packed": image.packed_file is not None}
        if image.source in FILE_IMAGE_SOURCES:
            paths = _image_files(image)
            record["file"] = paths[0]
            record["missing"] = not record["packed"] and not all(_exists(path) for path in paths)
        loaded = image.has_data
        width, height = (0, 0) if record.get("missing") else tuple(image.size)  # (loads the image)
        if not loaded and image.has_data and not image.is_dirty and hasattr(image, "buffers_free"):
            image.buffers_free()  # only measured here; Cycles loads what it needs itself
        record["size"] = [int(width), int(height)] if width and height else None
        records.append(record)
    return records


# --- what the file had -------------------------------------------------------------------


def source_settings(scene: "bpy.types.Scene", view_layer: "bpy.types.ViewLayer") -> dict:
    """The user's render settings before the protocol's are forced (recorded, not used)."""
    render = scene.render
    view = scene.view_settings
    record: dict[str, Any] = {
        "scene": scene.name,
        "engine": render.engine,
        "view_transform": view.view_transform,
        "look": view.look,
        "exposure": float(view.exposure),
        "gamma": float(view.gamma),
        "display_device": scene.display_settings.display_device,
        "film_transparent": bool(render.film_transparent),
        "resolution": [render.resolution_x, render.resolution_y],
        "resolution_percentage": render.resolution_percentage,
        "pixel_aspect": [float(render.pixel_aspect_x), float(render.pixel_aspect_y)],
        "frame_current": scene.frame_current,
        "use_freestyle": bool(render.use_freestyle),
        "view_layer": view_layer.name,
        "view_layers": [layer.name for layer in scene.view_layers if layer.use],
        "camera": None,
    }
    camera = scene.camera
    if camera is not None and camera.type == "CAMERA":
        data = camera.data
        record["camera"] = {
            "name": camera.name,
            "type": data.type,
            "lens_mm": float(data.lens),
            "sensor_width_mm": float(data.sensor_width),
            "sensor_height_mm": float(data.sensor_height),
            "sensor_fit": data.sensor_fit,
            "shift": [float(data.shift_x), float(data.shift_y)],
        }
    return record


def blend_identity(path: str) -> dict:
    """File, size and SHA-256 of a .blend, so --resume and --merge can tell a changed scene."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return {"file": os.path.abspath(path), "sha256": digest.hexdigest()}
