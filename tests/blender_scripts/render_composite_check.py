"""NeRF in Renders, as a user turns it on: F12 of a frame and of a short animation with the
run's NeRF composited by depth, beside what they are scored against. Imported by
``addon_session.py`` (the add-on installed, a run trained on the open scene, the scene's camera
keyed over frames 1-3); tests/test_addon.py scores the images.

The stage: the scene's own meshes are hidden from the render (the NeRF stands in for them); a
red cube stands between the camera and the NeRF, over part of it, and a green plane far behind
it fills the frame. Both glow (an emission shader), so Cycles renders them flat.

What is written into WORK/composite/:
- ``alone_NNNN.png``: Cycles alone, NeRF in Renders off, frames 1-3;
- ``f12_NNNN.png``: the same frames with it on (an animation render), ``still.png`` frame 2 by
  F12 (a still), ``eevee.png`` frame 2 by EEVEE where asked (after the first EEVEE render,
  each takes the bpy module about 50 s here);
- ``nerf/NNNN.png``: the NeRF's own ``render`` of each frame's camera at the render size.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import bpy
import mathutils

SIZE = (64, 48)
FRAMES = (1, 2, 3)


def flat_material(name: str, colour) -> bpy.types.Material:
    """Emission only: the same colour in Solid (object colour, flat light) and Rendered shading,
    by Cycles and EEVEE (also the GUI live view test's)."""
    material = bpy.data.materials.new(name)
    material.use_nodes = True
    nodes = material.node_tree.nodes
    nodes.clear()
    emission, output = nodes.new("ShaderNodeEmission"), nodes.new("ShaderNodeOutputMaterial")
    emission.inputs["Color"].default_value = (*colour, 1.0)
    material.node_tree.links.new(emission.outputs[0], output.inputs["Surface"])
    material.diffuse_color = (*colour, 1.0)
    return material


def _add_mesh(name: str, vertices, faces, material) -> bpy.types.Object:
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(vertices, [], faces)
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def stage(scene, centre: mathutils.Vector, radius: float) -> list:
    """The red cube in front and the green plane behind, placed in the camera's frame at frame 2."""
    scene.frame_set(2)
    camera = scene.camera.matrix_world.copy()
    to_camera = camera.inverted()
    distance = -(to_camera @ centre).z
    # The cube: halfway to the NeRF, a little left of the view's middle, a twelfth of the distance a side.
    middle = camera @ mathutils.Vector((-0.06 * distance, 0.0, -0.5 * distance))
    half = 0.04 * distance
    corners = [(x, y, z) for x in (-half, half) for y in (-half, half) for z in (-half, half)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    cube = _add_mesh("composite cube", [camera.to_3x3() @ mathutils.Vector(c) + middle for c in corners], faces,
                     flat_material("composite red", (1.0, 0.0, 0.0)))
    # The plane: facing the camera, a radius behind everything the NeRF holds, filling the frame.
    depth, extent = distance + 1.5 * radius, 10.0 * (distance + 1.5 * radius)
    quad = [(-extent, -extent), (extent, -extent), (extent, extent), (-extent, extent)]
    plane = _add_mesh("composite plane", [camera @ mathutils.Vector((x, y, -depth)) for x, y in quad], [(0, 1, 2, 3)],
                      flat_material("composite green", (0.0, 1.0, 0.0)))
    return [cube, plane]


def _render(scene, engine: str, path: Path, animation: bool) -> list:
    try:
        scene.render.engine = engine
    except TypeError:  # EEVEE is BLENDER_EEVEE_NEXT in 4.2-4.5
        scene.render.engine = "BLENDER_EEVEE_NEXT"
    scene.render.filepath = str(path)
    return sorted(bpy.ops.render.render(animation=animation, write_still=not animation))


def _tree_nodes(scene) -> list:
    tree = scene.compositing_node_group if hasattr(scene, "compositing_node_group") else scene.node_tree
    return sorted(node.name for node in tree.nodes) if tree is not None else []


def nerf_renders(context, module: str, out: Path) -> None:
    """The NeRF's own ``render`` of the camera at each frame, at the render size (the backend's
    command, not the server F12 uses)."""
    results_ops = sys.modules[f"{module}.blender.results_ops"]
    scene = context.scene
    world_to_nerf, _ = results_ops._dataset_camera_settings(context)
    intrinsics = results_ops._active_camera_intrinsics(context, *SIZE)
    frames = []
    for frame in FRAMES:
        scene.frame_set(frame)
        matrix = [list(row) for row in scene.camera.matrix_world]
        frames.append({"file_path": f"./{frame:04d}", "transform_matrix":
                       sys.modules["datasets_gen.core.camera_path"].camera_to_nerf(matrix, world_to_nerf)})
    keys = ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_angle_x")
    cameras = out / "cameras.json"
    cameras.write_text(json.dumps({**{k: intrinsics[k] for k in keys}, "frames": frames}))
    results_ops.run_backend(context, sys.modules["nerf_contract.commands"].render_cameras_argv(
        str(results_ops.run_dir(context)), str(cameras), str(out / "nerf")))


def run(context, module: str, work: Path, originals: list, eevee: bool = True) -> dict:
    """The whole check around ``originals``, the meshes the NeRF learnt (with the EEVEE render
    where ``eevee``); what it found, for the report."""
    import datasets_gen.core.camera_path  # noqa: F401  (from the extension's wheel: camera_to_nerf)

    corners = [obj.matrix_world @ mathutils.Vector(corner) for obj in originals for corner in obj.bound_box]
    low = mathutils.Vector([min(c[i] for c in corners) for i in range(3)])
    high = mathutils.Vector([max(c[i] for c in corners) for i in range(3)])
    centre, radius = (low + high) / 2, (high - low).length / 2
    scene, out = context.scene, work / "composite"
    out.mkdir(exist_ok=True)
    hidden = {obj.name: obj.hide_render for obj in scene.objects}
    for obj in scene.objects:
        obj.hide_render = obj.hide_render or obj.type == "MESH"
    added = stage(scene, centre, radius)
    render = scene.render
    saved = (render.resolution_x, render.resolution_y, render.resolution_percentage, render.film_transparent,
             scene.view_settings.view_transform, render.use_sequencer, render.engine, scene.cycles.samples)
    render.resolution_x, render.resolution_y, render.resolution_percentage = *SIZE, 100
    render.film_transparent, scene.view_settings.view_transform, render.use_sequencer = True, "Standard", False
    scene.cycles.samples, scene.cycles.device, scene.cycles.seed = 16, "CPU", 0
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    settings = scene.nerf
    report = {"folder": str(out), "nodes_before": _tree_nodes(scene)}
    report["alone"] = _render(scene, "CYCLES", out / "alone_", animation=True)
    report["turn_on"] = sorted(bpy.ops.nerf.render_composite())
    composite = sys.modules[f"{module}.blender.render_composite"]
    report["nodes_on"] = _tree_nodes(scene)
    report["animation"] = _render(scene, "CYCLES", out / "f12_", animation=True)
    scene.frame_set(2)
    report["still"] = _render(scene, "CYCLES", out / "still.png", animation=False)
    if eevee:
        report["eevee"] = _render(scene, "BLENDER_EEVEE", out / "eevee.png", animation=False)
    report["message"] = composite.last_message
    report["server_after"] = composite.client.state()
    report["turn_off"] = sorted(bpy.ops.nerf.render_composite())
    report["on_after"] = settings.render_composite
    report["nodes_after"] = _tree_nodes(scene)
    nerf_renders(context, module, out)
    for obj in added:
        bpy.data.objects.remove(obj)
    for obj in scene.objects:
        obj.hide_render = hidden.get(obj.name, obj.hide_render)
    (render.resolution_x, render.resolution_y, render.resolution_percentage, render.film_transparent,
     scene.view_settings.view_transform, render.use_sequencer, render.engine, scene.cycles.samples) = saved
    report["files"] = sorted(str(path.relative_to(out)) for path in out.rglob("*.png"))
    return report
