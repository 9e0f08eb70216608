"""The NeRF in F12 renders and animations: Cycles or EEVEE render the scene, the backend's
``serve`` renders the NeRF from the same camera at the render's size, and the compositor lays
one over the other by depth (a Z Combine of the render's Depth pass and the NeRF's camera z),
so a mesh in front of the NeRF hides it and one behind is hidden.

Turning **NeRF in Renders** on (``set_up``) adds the nodes to the scene's compositor, between
what feeds its output and the output, and turns on the view layer's Depth pass; turning it
off (``tear_down``) removes them and puts the old link back. The compositor's API differs:
``scene.node_tree`` with a Composite node in 4.x, ``scene.compositing_node_group`` with a
Group Output in 5.x. Render handlers do the rest: ``render_init`` starts a server (its own, not
the live view's, whose requests would replace F12's); for each frame, once the render's
depsgraph is at it (``frame_change_post``), the server renders the frame's camera into two
float images the nodes read; ``render_complete`` or ``render_cancel`` stops it. A frame the server cannot render leaves the images empty (the
scene alone) and says why on stderr and in the panel.
"""

from __future__ import annotations

import sys
from pathlib import Path

import bpy
import numpy as np

from nerf_contract.run_layout import CHECKPOINT_NAME

from ..core import sources
from ..core.composite_pixels import compositor_pixels, empty_pixels, render_size
from ..core.live_view import LiveViewClient
from .paths import backend_python
from .viewport_overlay import placement

COLOUR_IMAGE, DEPTH_IMAGE = "NeRF Render", "NeRF Render Depth"
NODE_PREFIX = "NeRF "  # the nodes set_up adds, found again by tear_down
Z_COMBINE, COLOUR_NODE, DEPTH_NODE, DEPTH_CHANNEL = (NODE_PREFIX + name for name in
                                                     ("Z Combine", "Colour", "Depth", "Depth Channel"))
FRAME_TIMEOUT_S = 600.0

client = LiveViewClient()
last_message = ""  # what the panel shows: the last render's NeRF frame, or why it is missing


# --- the compositor's nodes ----------------------------------------------------------------

def _tree(scene, create: bool):
    """The scene's compositing node tree (made where ``create`` and there is none)."""
    if hasattr(scene, "compositing_node_group"):  # Blender 5.0+
        tree = scene.compositing_node_group
        if tree is None and create:
            tree = bpy.data.node_groups.new("Compositing", "CompositorNodeTree")
            tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
            layers, output = tree.nodes.new("CompositorNodeRLayers"), tree.nodes.new("NodeGroupOutput")
            tree.links.new(layers.outputs["Image"], output.inputs[0])
            scene.compositing_node_group = tree
        return tree
    if create and not scene.use_nodes:
        scene.use_nodes = True  # 4.x: makes Render Layers → Composite where there was no tree
    return scene.node_tree if scene.use_nodes else None


def _output_node(tree):
    kinds = ("CompositorNodeComposite", "NodeGroupOutput")
    outputs = [node for node in tree.nodes if node.bl_idname in kinds]
    active = [node for node in outputs if getattr(node, "is_active_output", True)]
    return (active or outputs or [None])[0]


def _image(name: str, width: int, height: int):
    """The float image ``name`` at ``width`` × ``height`` (the same datablock kept: the nodes
    hold it)."""
    image = bpy.data.images.get(name)
    if image is None:
        image = bpy.data.images.new(name, width, height, alpha=True, float_buffer=True)
        image.colorspace_settings.name = _linear_colour_space()
    elif tuple(image.size) != (width, height):
        image.scale(width, height)
    return image


def _linear_colour_space() -> str:
    names = {item.identifier for item in bpy.types.ColorManagedInputColorspaceSettings.bl_rna.properties["name"].enum_items}
    return next(name for name in ("Linear Rec.709", "Linear") if name in names)


def _render_size(scene) -> tuple[int, int]:
    render = scene.render
    return render_size(render.resolution_x, render.resolution_y, render.resolution_percentage)


def set_up(scene) -> None:
    """The NeRF's nodes in the scene's compositor, the view layers' Depth pass on."""
    tree = _tree(scene, create=True)
    if tree.nodes.get(Z_COMBINE) is not None:
        return
    output = _output_node(tree)
    layers = next((node for node in tree.nodes if node.bl_idname == "CompositorNodeRLayers"), None)
    if output is None or layers is None:
        raise RuntimeError("the scene's compositor has no Render Layers node or no output: add them, then "
                           "turn NeRF in Renders on again")
    for view_layer in scene.view_layers:
        view_layer.use_pass_z = True
    width, height = _render_size(scene)
    colour, depth = tree.nodes.new("CompositorNodeImage"), tree.nodes.new("CompositorNodeImage")
    colour.image, depth.image = _image(COLOUR_IMAGE, width, height), _image(DEPTH_IMAGE, width, height)
    channel, combine = tree.nodes.new("CompositorNodeSeparateColor"), tree.nodes.new("CompositorNodeZcombine")
    for node, name in ((combine, Z_COMBINE), (colour, COLOUR_NODE), (depth, DEPTH_NODE), (channel, DEPTH_CHANNEL)):
        node.name = node.label = name
    combine.location = output.location.x - 200, output.location.y
    for offset, node in enumerate((colour, depth, channel)):
        node.location = combine.location.x - 250 * (1 + offset // 2), combine.location.y - 250 - 150 * (offset % 2)
    # Z Combine's inputs by place: the render and its depth, the NeRF and its depth (4.x names
    # them Image/Z, 5.x A/Depth A/B/Depth B); its options are properties in 4.x, inputs in 4.5+.
    feed = output.inputs[0].links[0].from_socket if output.inputs[0].is_linked else layers.outputs["Image"]
    links = tree.links
    links.new(feed, combine.inputs[0])
    links.new(layers.outputs["Depth"], combine.inputs[1])
    links.new(colour.outputs["Image"], combine.inputs[2])
    links.new(depth.outputs["Image"], channel.inputs[0])
    links.new(channel.outputs[0], combine.inputs[3])
    links.new(combine.outputs[0], output.inputs[0])
    # Alpha over by the front image's alpha (the NeRF's soft edges), without Z Combine's own
    # anti-aliasing, which blurs the choice across edges and tints the scene's pixels beside
    # the NeRF's silhouette.
    for option, socket, value in (("use_alpha", "Use Alpha", True), ("use_antialias_z", "Anti-Alias", False)):
        if hasattr(combine, option):
            setattr(combine, option, value)
        if socket in combine.inputs:
            combine.inputs[socket].default_value = value
    clear_images(scene)


def tear_down(scene) -> None:
    """Removes the NeRF's nodes and links what fed them to the output again."""
    tree = _tree(scene, create=False)
    combine = tree.nodes.get(Z_COMBINE) if tree is not None else None
    if combine is None:
        return
    feed = combine.inputs[0].links[0].from_socket if combine.inputs[0].is_linked else None
    targets = [link.to_socket for link in combine.outputs[0].links]
    for name in (Z_COMBINE, COLOUR_NODE, DEPTH_NODE, DEPTH_CHANNEL):
        node = tree.nodes.get(name)
        if node is not None:
            tree.nodes.remove(node)
    for socket in targets if feed is not None else ():
        tree.links.new(feed, socket)


def _write(image, pixels: np.ndarray) -> None:
    image.pixels.foreach_set(pixels)
    image.update()


def clear_images(scene) -> None:
    """Both images at the render's size, empty: the scene alone."""
    width, height = _render_size(scene)
    colour, depth = empty_pixels(width, height)
    _write(_image(COLOUR_IMAGE, width, height), colour)
    _write(_image(DEPTH_IMAGE, width, height), depth)


# --- the render handlers -------------------------------------------------------------------

_render = {"on": False}  # a render is in progress (set by render_init, cleared when it ends)


def _enabled(scene) -> bool:
    return scene is not None and scene.nerf.render_composite


def camera_request(scene, depsgraph) -> tuple[list, list, int, int]:
    """``(view matrix, projection matrix, width, height)`` of the camera ``depsgraph`` renders
    (its frame's, with markers' camera switches) at the scene's render size, as the server
    takes them (pixel aspect and shift included)."""
    camera = depsgraph.scene_eval.camera
    if camera is None:
        raise RuntimeError("the scene has no active camera")
    width, height = _render_size(scene)
    projection = camera.calc_matrix_camera(depsgraph, x=width, y=height, scale_x=scene.render.pixel_aspect_x,
                                           scale_y=scene.render.pixel_aspect_y)
    view = camera.matrix_world.inverted()
    return [list(row) for row in view], [list(row) for row in projection], width, height


def _say(message: str) -> None:
    global last_message
    last_message = message
    print(f"NeRF in Renders: {message}", file=sys.stderr if message.startswith("no NeRF") else sys.stdout)


@bpy.app.handlers.persistent
def _render_init(scene, *_args) -> None:
    if not _enabled(scene):
        return
    _render["on"] = True
    run = Path(bpy.path.abspath(scene.nerf.run_dir)).resolve()
    python = backend_python(bpy.context)
    if not python or not (run / CHECKPOINT_NAME).is_file():
        _say(f"no NeRF: {'no backend Python' if not python else f'{run}: no checkpoint yet'}")
        return
    client.start(python, sources.backend_root(), run, device=scene.nerf.train_device)


@bpy.app.handlers.persistent
def _render_pre(scene, *_args) -> None:
    """Before each frame: the images emptied, so a frame the NeRF misses shows the scene alone,
    never the frame before."""
    if _render["on"] and _enabled(scene):
        clear_images(scene)


@bpy.app.handlers.persistent
def _frame_changed(scene, depsgraph=None) -> None:
    """The render's depsgraph at the frame being rendered (after ``render_pre``, before the
    compositor): the NeRF from its camera into the images. ``render_pre`` itself sees the
    scene as it was when the render began, in animations too."""
    if not _render["on"] or depsgraph is None or depsgraph.mode != "RENDER" or not _enabled(scene):
        return
    frame_number = scene.frame_current
    if not client.running():
        _say(f"no NeRF in frame {frame_number}: the render server {client.state()}")
        return
    try:
        view, projection, width, height = camera_request(scene, depsgraph)
        frame = client.render(view, projection, width, height, nerf_to_world=placement(scene, client),
                              timeout=FRAME_TIMEOUT_S)
    except RuntimeError as error:
        _say(f"no NeRF in frame {frame_number}: {error}")
        return
    colour, depth = compositor_pixels(frame)
    _write(_image(COLOUR_IMAGE, width, height), colour)
    _write(_image(DEPTH_IMAGE, width, height), depth)
    _say(f"frame {frame_number}: the NeRF rendered in {frame.seconds:.2f} s (iteration {frame.iteration})")


@bpy.app.handlers.persistent
def _render_done(*_args) -> None:
    _render["on"] = False
    client.stop()


HANDLERS = (("render_init", _render_init), ("render_pre", _render_pre), ("frame_change_post", _frame_changed),
            ("render_complete", _render_done), ("render_cancel", _render_done))


def register() -> None:
    for name, handler in HANDLERS:
        getattr(bpy.app.handlers, name).append(handler)


def unregister() -> None:
    _render_done()
    for name, handler in HANDLERS:
        handlers = getattr(bpy.app.handlers, name)
        if handler in handlers:
            handlers.remove(handler)
