"""Where Blender's own ray casts hit a scene's rendered geometry, for the occupancy prior's test.

Run as `python ray_hits.py SCENE.blend OUT.json RAYS SEED` with a Python that has the bpy module.
The render geometry is set up here independently of datasets_gen: modifiers as they render,
subdivision at its render level.  Rays start at random points in and around the geometry's
bounds, half aimed at random points inside them, half in random directions; each ray goes on
through up to 8 surfaces, so hidden inner surfaces are hit too.  Writes {"hits": [[x, y, z],
...] (Blender world), "objects": [names hit]}.
"""

from __future__ import annotations

import json
import random
import sys

import bpy
from mathutils import Vector

PASSES = 8


def render_geometry(scene: "bpy.types.Scene") -> None:
    for obj in scene.objects:
        for modifier in obj.modifiers:
            modifier.show_viewport = modifier.show_render
            if modifier.type in ("SUBSURF", "MULTIRES"):
                modifier.levels = modifier.render_levels
    bpy.context.view_layer.update()


def world_bounds(depsgraph: "bpy.types.Depsgraph") -> tuple[Vector, Vector]:
    corners = [instance.matrix_world @ Vector(corner) for instance in depsgraph.object_instances
               if instance.object.type == "MESH" for corner in instance.object.bound_box]
    low = Vector([min(c[axis] for c in corners) for axis in range(3)])
    high = Vector([max(c[axis] for c in corners) for axis in range(3)])
    return low, high


def main() -> None:
    blend, out, rays, seed = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    bpy.ops.wm.open_mainfile(filepath=blend)
    scene = bpy.context.scene
    render_geometry(scene)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    low, high = world_bounds(depsgraph)
    size = high - low
    rng = random.Random(seed)

    def inside(grow: float) -> Vector:
        return Vector([low[a] - grow * size[a] + rng.random() * (1 + 2 * grow) * size[a] for a in range(3)])

    hits, objects = [], set()
    for index in range(rays):
        origin = inside(0.5)
        if index % 2 == 0:
            direction = (inside(0.0) - origin).normalized()
        else:
            direction = Vector([rng.gauss(0.0, 1.0) for _ in range(3)]).normalized()
        for _ in range(PASSES):
            found, location, _normal, _face, obj, _matrix = scene.ray_cast(depsgraph, origin, direction)
            if not found:
                break
            hits.append(list(location))
            objects.add(obj.name)
            origin = location + direction * (1e-5 * size.length)
    with open(out, "w") as handle:
        json.dump({"hits": hits, "objects": sorted(objects)}, handle)


if __name__ == "__main__":
    main()
