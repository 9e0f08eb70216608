"""Render the scene that is open, in-process (as the add-on will), and report what changed.

Run as `python open_scene_roundtrip.py SCENE.blend OUT_DIR REPORT.json` with a Python that has
the bpy module.  Opens SCENE.blend, records the scene's settings, calls
generate_dataset(scene=bpy.context.scene, ...), records them again and writes both records.
"""

from __future__ import annotations

import json
import os
import sys

import bpy

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from datasets_gen import generate_dataset  # noqa: E402

_SCALARS = {"BOOLEAN", "INT", "FLOAT", "STRING", "ENUM"}


def rna_values(owner) -> dict:
    """Every scalar and array property of an RNA struct, as plain JSON values."""
    values = {}
    for prop in owner.bl_rna.properties:
        if prop.identifier == "rna_type" or prop.type not in _SCALARS:
            continue
        value = getattr(owner, prop.identifier)
        if isinstance(value, set):
            value = sorted(value)
        elif not isinstance(value, (bool, int, float, str)):
            value = list(value)
        values[prop.identifier] = value
    return values


def state(scene) -> dict:
    def layer_collections(layer_collection, out):
        out[layer_collection.name] = [layer_collection.exclude, layer_collection.hide_viewport]
        for child in layer_collection.children:
            layer_collections(child, out)
        return out

    return {
        "render": rna_values(scene.render),
        "image_settings": rna_values(scene.render.image_settings),
        "cycles": rna_values(scene.cycles),
        "view_settings": rna_values(scene.view_settings),
        "display_settings": rna_values(scene.display_settings),
        "camera": scene.camera.name if scene.camera else None,
        "frame": scene.frame_current,
        "view_layers": {layer.name: rna_values(layer) for layer in scene.view_layers},
        "layer_collections": {layer.name: layer_collections(layer.layer_collection, {})
                              for layer in scene.view_layers},
        # (Not matrix_world: Blender computes it lazily, for viewport-hidden objects only once revealed.)
        "objects": {obj.name: [obj.hide_viewport, obj.hide_render, obj.hide_get(), list(obj.location),
                               list(obj.rotation_euler), list(obj.scale),
                               [m.show_viewport for m in obj.modifiers]] for obj in bpy.data.objects},
        "collections": {c.name: [c.hide_viewport, c.hide_render] for c in bpy.data.collections},
        "datablocks": {name: sorted(block.name for block in getattr(bpy.data, name))
                       for name in ("objects", "cameras", "meshes", "materials", "lights", "worlds", "scenes")},
        "cycles_device_type": bpy.context.preferences.addons["cycles"].preferences.compute_device_type,
    }


def main() -> None:
    blend, out_dir, report = sys.argv[-3:]
    bpy.ops.wm.open_mainfile(filepath=blend)
    scene = bpy.context.scene
    before = state(scene)
    generate_dataset(out_dir, scene=scene, width=24, height=16, train_views=2, val_views=0, test_views=1,
                     samples=2, progress=False)
    after = state(scene)
    with open(report, "w") as handle:
        json.dump({"before": before, "after": after}, handle)


if __name__ == "__main__":
    main()
