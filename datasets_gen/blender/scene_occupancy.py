"""The occupancy prior of a scene: its renderable triangles in the NeRF frame, voxelised.
The same triangles, collected once, are also the scene's true surface (surface_mesh).

The same objects as collect_geometry (scene_bounds): evaluated (modifiers, instances), only
what renders to the camera.  Meshable objects give their triangles (`loop_triangles` of
`to_mesh()` per instance); what to_mesh cannot measure (hair curves, point clouds, volumes)
is filled as its evaluated bounding box.  Geometry that renders beyond its mesh gets a margin
of its own: particle hair (its length) and true material displacement (the Displacement
node's scale; a box when the scale cannot be read).  Call with the render-visible objects
revealed (scene_bounds.reveal_render_visible), as the generator's survey leaves them.

Needs numpy (voxelise.py): the generator imports this module only when numpy is there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Iterator, Mapping, Optional

import bpy
import numpy as np
from mathutils import Vector

from nerf_contract.dataset_layout import APPEARANCE_REGIONS, PRIOR_NAME

from ..core.frame_fit import Similarity
from ..core.materials import NO_MATERIAL
from ..io.surface_mesh import NO_MATERIAL_INDEX
from ..core.voxelise import BASE_MARGIN_CELLS, DEFAULT_RESOLUTION, RULE, Occupancy, Part, margin_in_cells, voxelise
from .scene_bounds import MESHABLE_TYPES, SURFACE_OBJECT_TYPES, _camera_invisible_objects, _instances, slot_materials

MOTION_REASON = "motion: none, rendered with motion blur off"
BASE_REASON = (f"{BASE_MARGIN_CELLS} cell everywhere: the backend's grid is coarser than this one "
               "and its surface fuzzy")
#: How much a displaced object's bounding box grows when its displacement cannot be read.
UNREADABLE_DISPLACEMENT_GROWTH = 0.1


@dataclass
class _Margin:
    """An object's own margin and why: lengths that scale with the object, and world lengths."""

    object_units: float = 0.0
    world_units: float = 0.0
    reasons: list[str] = field(default_factory=list)
    fill_box: Optional[str] = None  # why the object must be filled as a (grown) box instead


@dataclass
class SceneParts:
    """The scene's geometry grouped by margin (NeRF units) and appearance region (an index into
    APPEARANCE_REGIONS), and what was filled as boxes, with why."""

    triangles: dict[tuple[float, int], list[np.ndarray]] = field(default_factory=dict)
    # Beside each array of ``triangles``, its triangles' materials (indices into the profile's
    # materials; NO_MATERIAL_INDEX where collect_parts was not told).
    materials: dict[tuple[float, int], list[np.ndarray]] = field(default_factory=dict)
    boxes: dict[tuple[float, int], list[np.ndarray]] = field(default_factory=dict)
    margin_reasons: dict[str, tuple[float, str]] = field(default_factory=dict)  # object -> (margin, why)
    filled_boxes: dict[str, str] = field(default_factory=dict)  # object -> why

    def all_triangles(self) -> np.ndarray:
        """[T, 3, 3] every meshed triangle, whatever its margin (the scene's true surface)."""
        return np.concatenate([np.zeros((0, 3, 3))] + [t for group in self.triangles.values() for t in group])

    def all_materials(self) -> np.ndarray:
        """[T] the material of each of ``all_triangles``, in the same order."""
        return np.concatenate([np.zeros(0, np.int64)] + [self.materials[key][i] for key, group in self.triangles.items()
                                                         for i in range(len(group))])

    def parts(self) -> list[Part]:
        empty = np.zeros((0, 3, 3))
        return [Part(np.concatenate(self.triangles.get(key, [empty])),
                     np.array(self.boxes.get(key, [])).reshape(-1, 2, 3), margin=key[0], region=key[1])
                for key in sorted(set(self.triangles) | set(self.boxes))]


def build_occupancy_prior(scene_parts: SceneParts,
                          resolution: int = DEFAULT_RESOLUTION) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(the profile's `occupancy_prior` record, the npz arrays) of collect_parts' geometry;
    ValueError when nothing can be voxelised."""
    occupancy = voxelise(scene_parts.parts(), resolution)
    return prior_record(occupancy, scene_parts), occupancy.arrays()


def collect_parts(view_layer: "bpy.types.ViewLayer", frame: Similarity,
                  region_of: Optional[Mapping[str, int]] = None,
                  material_of: Optional[Mapping[str, int]] = None) -> SceneParts:
    """Every renderable instance's triangles (or box) in the NeRF frame, grouped by margin and
    by the appearance region of their material slot's material (``region_of``: material name,
    or NO_MATERIAL, to its index into APPEARANCE_REGIONS; 0 for any it does not name), each
    triangle with its material (``material_of``: the same names to their index in the profile's
    materials; NO_MATERIAL_INDEX for any it does not name)."""
    region_of = region_of or {}
    material_of = material_of or {}
    view_layer.update()
    scene_parts = SceneParts()
    for obj, owner, matrix, renders in _instances(view_layer, _camera_invisible_objects(view_layer)):
        if obj.type not in SURFACE_OBJECT_TYPES or not renders:
            continue
        name = owner.original.name
        margin = _object_margin(obj)
        nerf_margin = (margin.object_units * _largest_scale(matrix) + margin.world_units) * frame.scale
        if margin.reasons and nerf_margin >= scene_parts.margin_reasons.get(name, (0.0, ""))[0]:
            scene_parts.margin_reasons[name] = (nerf_margin, "; ".join(margin.reasons))  # its largest instance
        names = slot_materials(obj)
        regions = [region_of.get(material, 0) for material in names]
        if margin.fill_box is None and obj.type in MESHABLE_TYPES:
            triangles, slots = _nerf_triangles(obj, matrix, frame)
            # A slot index past the object's slots renders with none (Blender's own rule).
            slot = np.minimum(slots, len(regions))
            by_triangle = np.array(regions + [region_of.get(NO_MATERIAL, 0)], np.int64)[slot]
            material = np.array([material_of.get(name, NO_MATERIAL_INDEX) for name in names]
                                + [material_of.get(NO_MATERIAL, NO_MATERIAL_INDEX)], np.int64)[slot]
            for region in np.unique(by_triangle).tolist():
                chosen = by_triangle == region
                scene_parts.triangles.setdefault((nerf_margin, region), []).append(triangles[chosen])
                scene_parts.materials.setdefault((nerf_margin, region), []).append(material[chosen])
            continue
        low, high = _nerf_box(obj, matrix, frame)
        if margin.fill_box is not None:
            scene_parts.filled_boxes[name] = margin.fill_box
            grow = UNREADABLE_DISPLACEMENT_GROWTH * float((high - low).max())
            low, high = low - grow, high + grow
        else:
            scene_parts.filled_boxes[name] = (f"a {obj.type} object, which to_mesh cannot measure: "
                                              "its evaluated bounding box")
        scene_parts.boxes.setdefault((nerf_margin, max(regions)), []).append(np.stack([low, high]))
    return scene_parts


def prior_record(occupancy: Occupancy, scene_parts: SceneParts) -> dict[str, Any]:
    """The `occupancy_prior` entry of scene_profile.json."""
    grid = occupancy.grid
    reasons = [BASE_REASON, MOTION_REASON]
    for name, (margin, why) in sorted(scene_parts.margin_reasons.items()):
        reasons.append(f"{name}: +{margin_in_cells(margin, grid.cell_size)} cells "
                       f"({margin:.4g} NeRF units): {why}")
    surface_cells = max(int(occupancy.surface.sum()), 1)
    counts = np.bincount(occupancy.regions.ravel(), minlength=len(APPEARANCE_REGIONS))
    return {
        "file": PRIOR_NAME,
        # Each appearance region's share of the surface cells (the npz's `regions`; a cell two
        # regions share holds the later of APPEARANCE_REGIONS).
        "regions": {name: float(counts[index]) / surface_cells
                    for index, name in enumerate(APPEARANCE_REGIONS) if index and counts[index]},
        "resolution": list(grid.shape),
        "box_min": [float(value) for value in grid.box_min],
        "box_max": [float(value) for value in grid.box_max],
        "cell_size": float(grid.cell_size),
        "margin": {"cells": BASE_MARGIN_CELLS, "reasons": reasons},
        "surface_fraction": float(occupancy.surface.mean()),
        "solid_fraction": float(occupancy.solid.mean()),
        "filled_boxes": [f"{name}: {why}" for name, why in sorted(scene_parts.filled_boxes.items())],
        "rule": RULE,
    }


def _nerf_triangles(obj: "bpy.types.Object", matrix: Any, frame: Similarity) -> tuple[np.ndarray, np.ndarray]:
    """[T, 3, 3] the evaluated mesh's triangles (loop triangles) in the NeRF frame, and [T] the
    material slot index of each."""
    mesh = obj.to_mesh()
    try:
        if hasattr(mesh, "calc_loop_triangles"):  # needed before Blender 4.x computes them on access
            mesh.calc_loop_triangles()
        vertices = np.empty(3 * len(mesh.vertices), np.float32)
        mesh.vertices.foreach_get("co", vertices)
        corners = np.empty(3 * len(mesh.loop_triangles), np.int32)
        mesh.loop_triangles.foreach_get("vertices", corners)
        slots = np.empty(len(mesh.loop_triangles), np.int32)
        mesh.loop_triangles.foreach_get("material_index", slots)
    finally:
        obj.to_mesh_clear()
    to_nerf = _to_nerf_matrix(matrix, frame)
    points = vertices.reshape(-1, 3).astype(np.float64) @ to_nerf[:3, :3].T + to_nerf[:3, 3]
    return points[corners].reshape(-1, 3, 3), slots


def _nerf_box(obj: "bpy.types.Object", matrix: Any, frame: Similarity) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of the object's evaluated bounding box, transformed, in the NeRF frame."""
    corners = np.array([tuple(matrix @ Vector(corner)) for corner in obj.bound_box], np.float64)
    points = frame.scale * corners + np.asarray(frame.translation)
    return points.min(axis=0), points.max(axis=0)


def _to_nerf_matrix(matrix: Any, frame: Similarity) -> np.ndarray:
    to_nerf = np.array(frame.matrix(), np.float64)
    return to_nerf @ np.array([tuple(row) for row in matrix], np.float64)


def _largest_scale(matrix: Any) -> float:
    """The largest factor by which the instance's matrix stretches a length."""
    return float(max(abs(value) for value in matrix.to_scale()))


def _object_margin(obj: "bpy.types.Object") -> _Margin:
    """Geometry the mesh does not hold: particle hair, true displacement (object units)."""
    margin = _Margin()
    for length, why in _hair_lengths(obj):
        margin.object_units = max(margin.object_units, length)
        margin.reasons.append(why)
    for material in _materials(obj):
        displacement, world_space, why = _displacement(material)
        if why is None:
            continue
        if displacement is None:
            margin.fill_box = f"{why}: its evaluated bounding box grown by {UNREADABLE_DISPLACEMENT_GROWTH:.0%}"
        elif world_space:
            margin.world_units = max(margin.world_units, displacement)
            margin.reasons.append(why)
        else:
            margin.object_units = max(margin.object_units, displacement)
            margin.reasons.append(why)
    return margin


def _hair_lengths(obj: "bpy.types.Object") -> Iterator[tuple[float, str]]:
    """(reach in object units, why) of each rendered hair particle system."""
    for modifier in getattr(obj, "modifiers", ()):
        if modifier.type != "PARTICLE_SYSTEM" or not modifier.show_render:
            continue
        settings = modifier.particle_system.settings
        if settings.type != "HAIR" or settings.render_type == "NONE":
            continue
        # Simple children sit up to child_radius away from their parent hair.
        spread = settings.child_radius if settings.child_type == "SIMPLE" else 0.0
        yield (settings.hair_length + spread,
               f"hair particle system {settings.name!r}: hair length {settings.hair_length:.4g}"
               + (f" + children radius {spread:.4g}" if spread else "") + " x object scale")


def _materials(obj: "bpy.types.Object") -> list["bpy.types.Material"]:
    return [slot.material for slot in getattr(obj, "material_slots", ()) if slot.material is not None]


def _displacement(material: "bpy.types.Material") -> tuple[Optional[float], bool, Optional[str]]:
    """(largest displacement, in world space?, why) of a material that truly displaces.

    (None, _, None): no displacement (bump only, or nothing linked); (None, _, why): it displaces
    by an amount that cannot be read (a linked scale, vector displacement...).  With height
    in [0, 1], (height - midlevel) * scale never exceeds scale * max(1, |midlevel|, |1 - midlevel|).
    """
    method = getattr(material, "displacement_method", None) or getattr(
        getattr(material, "cycles", None), "displacement_method", "BUMP")
    tree = material.node_tree if getattr(material, "use_nodes", True) else None
    output = tree.get_output_node("CYCLES") if tree is not None else None
    socket = output.inputs.get("Displacement") if output is not None else None
    if method == "BUMP" or socket is None or not socket.is_linked:
        return None, False, None
    node = _through_reroutes(socket.links[0].from_node)
    what = f"material {material.name!r} displaces ({method})"
    if node.type != "DISPLACEMENT" or node.inputs["Scale"].is_linked or node.inputs["Midlevel"].is_linked:
        return None, False, f"{what} by an amount that cannot be read ({node.bl_idname})"
    scale = abs(node.inputs["Scale"].default_value)
    midlevel = node.inputs["Midlevel"].default_value
    reach = scale * max(1.0, abs(midlevel), abs(1.0 - midlevel))
    world_space = getattr(node, "space", "OBJECT") == "WORLD"
    units = "world units" if world_space else "object units x object scale"
    return reach, world_space, f"{what}: Displacement node scale {scale:.4g}, midlevel {midlevel:.4g} ({units})"


def _through_reroutes(node: "bpy.types.Node") -> "bpy.types.Node":
    while node.type == "REROUTE" and node.inputs[0].is_linked:
        node = node.inputs[0].links[0].from_node
    return node
