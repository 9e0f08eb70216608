"""What renders, where: the renderable geometry's bounds, bounding sphere, materials and lights.

The fit transform and the backend's sampling box come from these, so they use the evaluated
geometry (modifiers, geometry-node instances, curve bevels) of exactly what the camera sees:
objects and collections hidden from render, excluded or indirect-only collections and objects
invisible to camera rays are left out.  Blender only evaluates what the viewport shows, so
objects hidden in the viewport but rendered are revealed first (through the journal, undone
afterwards) and modifiers take their render visibility.

Pure Python over vertices keeps it numpy-free (Blender builds without numpy exist): fast
enough for scenes of a few million vertices.
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass, field
from typing import Iterator, Optional

import bpy
from mathutils import Vector

from ..core.frame_fit import bounding_sphere_radius
from ..core.materials import NO_MATERIAL
from .scene_state import SettingsJournal

#: Object types whose evaluated geometry can be turned into a mesh and appears in renders.
SURFACE_OBJECT_TYPES = {"MESH", "CURVE", "SURFACE", "FONT", "META", "CURVES", "POINTCLOUD", "VOLUME"}
#: Of those, the ones `to_mesh` can measure (hair curves, point clouds and volumes cannot).
MESHABLE_TYPES = {"MESH", "CURVE", "SURFACE", "FONT", "META"}


@dataclass
class Geometry:
    """The renderable part of a scene, in Blender's world."""

    low: Optional[list[float]] = None
    high: Optional[list[float]] = None
    radius: float = 0.0  # farthest vertex from the centre of [low, high]
    objects: list[str] = field(default_factory=list)  # renderable surface objects (instancers named)
    hidden: list[str] = field(default_factory=list)  # surface objects left out (hidden from render/camera)
    others: list[str] = field(default_factory=list)  # non-surface objects (lights, empties, rigs...)
    materials: dict[str, list[str]] = field(default_factory=dict)  # material name -> objects using it
    lights: list[dict] = field(default_factory=list)  # render-visible lights, Blender world

    @property
    def centre(self) -> list[float]:
        assert self.low is not None and self.high is not None
        return [(lo + hi) / 2.0 for lo, hi in zip(self.low, self.high)]


def render_view_layer(scene: "bpy.types.Scene") -> "bpy.types.ViewLayer":
    """The view layer the dataset renders: the active one if it renders, else the first that does."""
    active = getattr(bpy.context, "view_layer", None)
    if bpy.context.scene == scene and active is not None and active.use:
        for layer in scene.view_layers:
            if layer == active:
                return layer
    for layer in scene.view_layers:
        if layer.use:
            return layer
    return scene.view_layers[0]


def reveal_render_visible(scene: "bpy.types.Scene", view_layer: "bpy.types.ViewLayer",
                          journal: SettingsJournal) -> None:
    """Make what renders also evaluate in the viewport depsgraph (undone by the journal).

    Objects disabled in viewports or hidden with H are not evaluated at all; collections can
    be disabled in viewports; modifiers can differ between viewport and render, and so can
    subdivision levels, particle amounts and the scene's Simplify settings.
    """
    def walk(layer_collection: "bpy.types.LayerCollection") -> None:
        collection = layer_collection.collection
        if layer_collection.exclude or collection.hide_render:
            return
        if layer_collection.hide_viewport:
            journal.set(layer_collection, "hide_viewport", False)
        if collection.hide_viewport:
            journal.set(collection, "hide_viewport", False)
        for child in layer_collection.children:
            walk(child)

    walk(view_layer.layer_collection)
    for obj in scene.objects:
        if obj.hide_render:
            continue
        if obj.hide_viewport:
            journal.set(obj, "hide_viewport", False)
        if obj.hide_get(view_layer=view_layer):
            obj.hide_set(False, view_layer=view_layer)
            journal.on_restore(f"{obj.name} hidden", lambda o=obj: o.hide_set(True, view_layer=view_layer))
        for modifier in obj.modifiers:
            if modifier.show_viewport != modifier.show_render:
                journal.set(modifier, "show_viewport", modifier.show_render)
            _render_amounts(modifier, journal)
    if scene.render.use_simplify:
        journal.set(scene.render, "simplify_subdivision", scene.render.simplify_subdivision_render)
        journal.set(scene.render, "simplify_child_particles", scene.render.simplify_child_particles_render)
    view_layer.update()


def _render_amounts(modifier: "bpy.types.Modifier", journal: SettingsJournal) -> None:
    """Evaluate a modifier's render amount (subdivision levels, particle counts), not its viewport one.

    A surface subdivided only for render lies inside its cage: the occupancy prior must see it.
    """
    if modifier.type in ("SUBSURF", "MULTIRES"):
        journal.set(modifier, "levels", modifier.render_levels)
    if modifier.type == "PARTICLE_SYSTEM" and modifier.show_render:
        settings = modifier.particle_system.settings
        journal.set(settings, "display_percentage", 100)
        for display_children in ("child_percent", "child_nbr"):  # Blender 5 / 3.4 spelling
            journal.set_if_present(settings, display_children, settings.rendered_child_count)


def _camera_invisible_objects(view_layer: "bpy.types.ViewLayer") -> set[str]:
    """Objects only in collections that do not render to the camera (hidden, excluded, indirect-only)."""
    hidden: set[str] = set()
    visible: set[str] = set()

    def walk(layer_collection: "bpy.types.LayerCollection", parent_hidden: bool) -> None:
        collection = layer_collection.collection
        is_hidden = (parent_hidden or collection.hide_render or layer_collection.exclude
                     or layer_collection.indirect_only)
        for obj in collection.objects:
            (hidden if is_hidden else visible).add(obj.name)
        for child in layer_collection.children:
            walk(child, is_hidden)

    walk(view_layer.layer_collection, False)
    return hidden - visible


def _renders(obj: "bpy.types.Object", hidden_names: set[str]) -> bool:
    original = obj.original
    return not (original.hide_render or original.name in hidden_names
                or not getattr(original, "visible_camera", True))


def _instances(
    view_layer: "bpy.types.ViewLayer", hidden_names: set[str]
) -> Iterator[tuple["bpy.types.Object", "bpy.types.Object", object, bool]]:
    """(evaluated object, its owner: the instancer or itself, world matrix, renders) per instance.

    An instance renders when its instancer does and the instanced object is not itself hidden
    from render; the instanced object's own collections do not matter (a common set-up keeps
    the source collection excluded and instances it elsewhere).
    """
    for instance in view_layer.depsgraph.object_instances:
        obj = instance.object
        if instance.is_instance and instance.parent:
            owner = instance.parent
            renders = _renders(owner, hidden_names) and _renders(obj, set())
        else:
            owner = obj
            renders = _renders(obj, hidden_names)
        yield obj, owner, instance.matrix_world.copy(), renders


def collect_geometry(scene: "bpy.types.Scene", view_layer: "bpy.types.ViewLayer") -> Geometry:
    """Bounds, bounding sphere, objects, materials and lights of what renders (call after reveal)."""
    view_layer.update()
    hidden_names = _camera_invisible_objects(view_layer)
    geometry = Geometry()
    points = array("d")
    renderable: set[str] = set()
    for obj, owner, matrix, renders in _instances(view_layer, hidden_names):
        if obj.type == "LIGHT":
            if not (owner.original.hide_render or owner.original.name in hidden_names):
                geometry.lights.append(_light_record(obj, matrix))
            continue
        if obj.type not in SURFACE_OBJECT_TYPES or not renders:
            continue
        renderable.add(owner.original.name)
        for name in slot_materials(obj):
            users = geometry.materials.setdefault(name, [])
            if owner.original.name not in users:
                users.append(owner.original.name)
        if obj.type in MESHABLE_TYPES:
            _append_vertices(obj, matrix, points)
        else:
            _append_box(obj, matrix, points)
    geometry.objects = sorted(renderable)
    for obj in scene.objects:
        if obj.name in renderable:
            continue
        (geometry.hidden if obj.type in SURFACE_OBJECT_TYPES else geometry.others).append(obj.name)
    if points:
        low = [min(points[axis::3]) for axis in range(3)]
        high = [max(points[axis::3]) for axis in range(3)]
        geometry.low, geometry.high = low, high
        geometry.radius = bounding_sphere_radius(geometry.centre, points)
    return geometry


def slot_materials(obj: "bpy.types.Object") -> list[str]:
    """The material name of each of the object's slots (NO_MATERIAL for an empty one); one
    NO_MATERIAL for an object with no slots."""
    return [slot.material.name if slot.material else NO_MATERIAL
            for slot in getattr(obj, "material_slots", ())] or [NO_MATERIAL]


def _append_vertices(obj: "bpy.types.Object", matrix: object, points: "array[float]") -> None:
    mesh = obj.to_mesh()
    try:
        coordinates = array("f", bytes(4 * 3 * len(mesh.vertices)))
        mesh.vertices.foreach_get("co", coordinates)
    finally:
        obj.to_mesh_clear()
    rows = [tuple(matrix[r]) for r in range(3)]  # type: ignore[index]
    (a0, a1, a2, a3), (b0, b1, b2, b3), (c0, c1, c2, c3) = rows
    for start in range(0, len(coordinates), 3):
        x, y, z = coordinates[start], coordinates[start + 1], coordinates[start + 2]
        points.extend((a0 * x + a1 * y + a2 * z + a3, b0 * x + b1 * y + b2 * z + b3, c0 * x + c1 * y + c2 * z + c3))


def _append_box(obj: "bpy.types.Object", matrix: object, points: "array[float]") -> None:
    """Hair curves, point clouds, volumes: their evaluated bounding box corners stand in for vertices."""
    for corner in obj.bound_box:
        world = matrix @ Vector(corner)  # type: ignore[operator]
        points.extend((world.x, world.y, world.z))


def _light_record(obj: "bpy.types.Object", matrix: object) -> dict:
    light = obj.data
    direction = -Vector([matrix[r][2] for r in range(3)]).normalized()  # type: ignore[index]
    return {
        "name": obj.original.name,
        "type": light.type,
        "energy": float(light.energy),
        "color": [float(c) for c in light.color],
        "location_blender": [float(matrix[r][3]) for r in range(3)],  # type: ignore[index]
        "direction": [float(c) for c in direction],
    }
