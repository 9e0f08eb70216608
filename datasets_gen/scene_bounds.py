"""World-space bounds of everything that renders as a surface, as Blender evaluates it.

The NeRF backend sets its near/far planes and sampling box from these bounds, so they use the
evaluated geometry (modifiers, geometry-node instances, curve bevels) rather than the objects'
unevaluated bound boxes.  Pure Python over vertices keeps it numpy-free (Blender builds without
numpy exist); that is fast enough for the demo and for scenes of a few million vertices.
"""

from __future__ import annotations

from array import array
from typing import Iterator, Optional

import bpy

from .options import DatasetGenError

#: Object types whose evaluated geometry can be turned into a mesh and appears in renders.
SURFACE_OBJECT_TYPES = {"MESH", "CURVE", "SURFACE", "FONT", "META"}

Bounds = tuple[list[float], list[float]]


def _render_hidden_collection_objects(scene: "bpy.types.Scene") -> set[str]:
    """Names of objects that sit only inside collections disabled for rendering."""
    hidden: set[str] = set()
    visible: set[str] = set()

    def walk(collection: "bpy.types.Collection", parent_hidden: bool) -> None:
        is_hidden = parent_hidden or collection.hide_render
        for obj in collection.objects:
            (hidden if is_hidden else visible).add(obj.name)
        for child in collection.children:
            walk(child, is_hidden)

    walk(scene.collection, False)
    return hidden - visible


def _renderable_instances(
    depsgraph: "bpy.types.Depsgraph", hidden_names: set[str]
) -> Iterator[tuple["bpy.types.Object", "object"]]:
    """(evaluated object, world matrix) of each surface instance that is visible to the camera."""
    for instance in depsgraph.object_instances:
        obj = instance.object
        if obj.type not in SURFACE_OBJECT_TYPES:
            continue
        owner = instance.parent if instance.is_instance and instance.parent else obj
        original = owner.original
        if original.hide_render or original.name in hidden_names:
            continue
        if not getattr(obj.original, "visible_camera", True):
            continue
        yield obj, instance.matrix_world.copy()


def scene_bounds(scene: "bpy.types.Scene") -> Bounds:
    """Axis-aligned (min, max) of all renderable surface geometry in world space.

    Raises DatasetGenError when the scene has no such geometry (nothing to reconstruct).
    Objects hidden only in the viewport are not in Blender's viewport depsgraph and are missed.
    """
    view_layer = scene.view_layers[0]
    view_layer.update()
    depsgraph = view_layer.depsgraph
    hidden_names = _render_hidden_collection_objects(scene)
    low: Optional[list[float]] = None
    high: Optional[list[float]] = None
    for obj, matrix in _renderable_instances(depsgraph, hidden_names):
        mesh = obj.to_mesh()
        try:
            coordinates = array("f", bytes(4 * 3 * len(mesh.vertices)))
            mesh.vertices.foreach_get("co", coordinates)
        finally:
            obj.to_mesh_clear()
        if not coordinates:
            continue
        rows = [tuple(matrix[r]) for r in range(3)]
        for start in range(0, len(coordinates), 3):
            x, y, z = coordinates[start], coordinates[start + 1], coordinates[start + 2]
            point = [m0 * x + m1 * y + m2 * z + m3 for m0, m1, m2, m3 in rows]
            if low is None or high is None:
                low, high = list(point), list(point)
                continue
            for axis in range(3):
                if point[axis] < low[axis]:
                    low[axis] = point[axis]
                elif point[axis] > high[axis]:
                    high[axis] = point[axis]
    if low is None or high is None:
        raise DatasetGenError(f"scene {scene.name!r} has no renderable mesh or curve geometry")
    return low, high
