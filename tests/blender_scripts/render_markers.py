"""Render tiny emissive markers with given cameras, for the intrinsics tests.

Run as `python render_markers.py CASES.json OUT_DIR` with a Python that has the bpy module.
Each case renders a black scene holding three small emissive spheres (pure red, green, blue,
so each marker can be located in its own channel) and writes OUT_DIR/<name>.npy (linear RGB
float32, rows top to bottom) and OUT_DIR/<name>.json (camera settings and matrix_world as
Blender reports them after the view layer update).  The test does the projecting.
"""

from __future__ import annotations

import json
import os
import sys

import bpy
import numpy as np

MARKER_RADIUS = 0.03


def build_scene(markers: list[list[float]]) -> bpy.types.Scene:
    """A new scene: black world, three emissive spheres, one camera; Cycles, raw colours."""
    import bmesh

    scene = bpy.data.scenes.new("markers")
    world = bpy.data.worlds.new("black")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
    scene.world = world
    for index, location in enumerate(markers):
        mesh = bpy.data.meshes.new(f"marker{index}")
        bm = bmesh.new()
        bmesh.ops.create_uvsphere(bm, u_segments=16, v_segments=8, radius=MARKER_RADIUS)
        bm.to_mesh(mesh)
        bm.free()
        material = bpy.data.materials.new(f"emit{index}")
        if material.node_tree is None:
            material.use_nodes = True
        nodes = material.node_tree.nodes
        for node in list(nodes):
            if node.type != "OUTPUT_MATERIAL":
                nodes.remove(node)
        emission = nodes.new("ShaderNodeEmission")
        colour = [0.0, 0.0, 0.0, 1.0]
        colour[index] = 1.0
        emission.inputs["Color"].default_value = colour
        emission.inputs["Strength"].default_value = 1.0
        output = next(n for n in nodes if n.type == "OUTPUT_MATERIAL")
        material.node_tree.links.new(emission.outputs[0], output.inputs["Surface"])
        mesh.materials.append(material)
        obj = bpy.data.objects.new(f"marker{index}", mesh)
        obj.location = location
        scene.collection.objects.link(obj)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.max_bounces = 0
    scene.render.film_transparent = False
    scene.render.dither_intensity = 0.0
    scene.view_settings.view_transform = "Raw"
    scene.view_settings.look = "None"
    settings = scene.render.image_settings
    settings.file_format = "OPEN_EXR"
    settings.color_depth = "32"
    return scene


def render_case(scene: bpy.types.Scene, case: dict, out_dir: str) -> None:
    """Apply one camera case, render it and dump pixels and the camera as Blender sees it."""
    from mathutils import Matrix

    camera = scene.camera
    data = camera.data
    data.lens = case["lens"]
    data.sensor_width = case["sensor_width"]
    data.sensor_height = case["sensor_height"]
    data.sensor_fit = case["sensor_fit"]
    data.shift_x, data.shift_y = case["shift"]
    camera.matrix_world = Matrix(case["matrix_world"])
    render = scene.render
    render.resolution_x, render.resolution_y = case["resolution"]
    render.resolution_percentage = case["percentage"]
    render.pixel_aspect_x, render.pixel_aspect_y = case["pixel_aspect"]
    scene.cycles.samples = case["samples"]
    scene.view_layers[0].update()

    bpy.ops.render.render(scene=scene.name)
    path = os.path.join(out_dir, case["name"] + ".exr")
    bpy.data.images["Render Result"].save_render(filepath=path, scene=scene)
    image = bpy.data.images.load(path)
    width, height = image.size
    pixels = np.empty(width * height * image.channels, dtype=np.float32)
    image.pixels.foreach_get(pixels)
    rgb = pixels.reshape(height, width, image.channels)[::-1, :, :3]
    bpy.data.images.remove(image)
    np.save(os.path.join(out_dir, case["name"] + ".npy"), np.ascontiguousarray(rgb))
    record = {
        "matrix_world": [list(row) for row in camera.matrix_world],
        "lens": data.lens,
        "sensor_width": data.sensor_width,
        "sensor_height": data.sensor_height,
        "sensor_fit": data.sensor_fit,
        "shift": [data.shift_x, data.shift_y],
        "resolution": [render.resolution_x, render.resolution_y],
        "percentage": render.resolution_percentage,
        "pixel_aspect": [render.pixel_aspect_x, render.pixel_aspect_y],
    }
    with open(os.path.join(out_dir, case["name"] + ".json"), "w") as handle:
        json.dump(record, handle)


def main() -> None:
    cases_path, out_dir = sys.argv[1], sys.argv[2]
    with open(cases_path) as handle:
        spec = json.load(handle)
    scene = build_scene(spec["markers"])
    for case in spec["cases"]:
        render_case(scene, case, out_dir)


if __name__ == "__main__":
    main()
