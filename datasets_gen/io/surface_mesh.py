"""The scene's true surface as a file: its renderable triangles in the NeRF frame, welded into a
mesh and written as binary PLY (`scene_geometry.ply`), so that a NeRF's geometry can be measured
against it (the backend's `eval --geometry`).

The triangles are the occupancy prior's (scene_occupancy.collect_parts: evaluated, after
modifiers and instancing, only what renders to the camera), so the scene is walked once for
both.  What to_mesh cannot measure (hair curves, point clouds, volumes, displacement that cannot
be read) is left out, and the profile's record says so; geometry that renders beyond its mesh
(particle hair, readable displacement) is in the file as its mesh, and the record names it.

numpy only, no bpy (the generator imports this module only when numpy is there).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nerf_contract.dataset_layout import GEOMETRY_NAME

from .output_dir import write_file_atomic

FRAME = "NeRF frame: p_nerf = scale * p_blender + translation (world_to_nerf)"
# Each face's material: an element of its own after the faces (``face_material``, one ushort a
# face: the material's index in the profile's ``materials``), so that a reader of vertices and
# faces alone skips it. NO_MATERIAL_INDEX: a face whose material the profile does not list.
MATERIAL_ELEMENT = "face_material"
NO_MATERIAL_INDEX = 65535


def weld(triangles: np.ndarray, materials: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(vertices [V, 3] float32, faces [T, 3] int32, materials [T] uint16 or None) of triangles
    [T, 3, 3] and their ``materials``: corners that are the same point (as float32) become one
    vertex, so the file is a connected mesh.

    The order is canonical (vertices sorted; each face turned to start at its lowest vertex, its
    winding kept; faces sorted): Blender lists an n-gon's triangles in an order that varies from
    run to run, and the same scene must give the same file (shards, --resume).

    >>> square = np.array([[[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[1, 1, 0], [0, 1, 0], [0, 0, 0]]], float)
    >>> vertices, faces, materials = weld(square, np.array([7, 3]))
    >>> vertices.tolist(), faces.tolist(), materials.tolist()
    ([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]], [[0, 2, 3], [0, 3, 1]], [7, 3])
    """
    corners = np.ascontiguousarray(triangles, dtype=np.float32).reshape(-1, 3)
    vertices, index = np.unique(corners, axis=0, return_inverse=True)
    faces = index.reshape(-1, 3)
    turn = (faces.argmin(axis=1)[:, None] + np.arange(3)) % 3
    faces = np.take_along_axis(faces, turn, axis=1)
    order = np.lexsort(faces.T[::-1])
    return (vertices, faces[order].astype(np.int32),
            None if materials is None else np.asarray(materials)[order].astype(np.uint16))


def ply_bytes(vertices: np.ndarray, faces: np.ndarray, materials: np.ndarray | None = None) -> bytes:
    """A binary little-endian PLY of float xyz vertices and triangle faces, and each face's
    material (MATERIAL_ELEMENT) where given."""
    face = np.empty(len(faces), dtype=[("count", "u1"), ("indices", "<i4", (3,))])
    face["count"] = 3
    face["indices"] = faces
    header = (f"ply\nformat binary_little_endian 1.0\ncomment the scene's renderable triangles, {FRAME}\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\n")
    body = np.ascontiguousarray(vertices, dtype="<f4").tobytes() + face.tobytes()
    if materials is not None:
        header += f"element {MATERIAL_ELEMENT} {len(faces)}\nproperty ushort material\n"
        body += np.ascontiguousarray(materials, dtype="<u2").tobytes()
    return (header + "end_header\n").encode("ascii") + body


def read_ply(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [V, 3] float32, faces [T, 3] int32) of a file ``ply_bytes`` wrote (and only such)."""
    with open(path, "rb") as handle:
        data = handle.read()
    end = data.find(b"end_header\n")
    header = data[:end].decode("ascii", "replace").splitlines() if end > 0 else []
    counts = {line.split()[1]: int(line.split()[2]) for line in header if line.startswith("element ")}
    if (not header or header[:2] != ["ply", "format binary_little_endian 1.0"]
            or set(counts) - {MATERIAL_ELEMENT} != {"vertex", "face"}):
        raise ValueError(f"{path}: not the scene geometry file datasets_gen writes")
    body = data[end + len(b"end_header\n"):]
    vertex_bytes = 12 * counts["vertex"]
    face = np.dtype([("count", "u1"), ("indices", "<i4", (3,))])
    expected = vertex_bytes + face.itemsize * counts["face"] + 2 * counts.get(MATERIAL_ELEMENT, 0)
    if len(body) != expected:
        raise ValueError(f"{path}: {len(body)} bytes of vertices and faces, expected {expected} (a truncated file?)")
    vertices = np.frombuffer(body[:vertex_bytes], dtype="<f4").reshape(-1, 3)
    faces = np.frombuffer(body[vertex_bytes:vertex_bytes + face.itemsize * counts["face"]], dtype=face)["indices"]
    return vertices.astype(np.float32), faces.astype(np.int32)


def write_ply_atomic(path: str, vertices: np.ndarray, faces: np.ndarray, materials: np.ndarray | None = None) -> None:
    write_file_atomic(path, lambda handle: handle.write(ply_bytes(vertices, faces, materials)))


def geometry_record(triangle_count: int, vertex_count: int, left_out: dict[str, str],
                    beyond_mesh: dict[str, tuple[float, str]]) -> dict[str, Any]:
    """The profile's `geometry` entry: the file, its size and frame, and what it does not hold
    exactly (objects left out, with why; objects that render beyond their mesh, by how much).

    >>> record = geometry_record(12, 8, {"Strands": "a CURVES object"}, {"Hairy": (0.25, "hair length 0.5")})
    >>> record["file"], record["left_out"], record["beyond_mesh"]
    ('scene_geometry.ply', ['Strands: a CURVES object'], ['Hairy: up to 0.25 NeRF units: hair length 0.5'])
    """
    return {
        "file": GEOMETRY_NAME,
        "triangles": triangle_count,
        "vertices": vertex_count,
        "frame": FRAME,
        "left_out": [f"{name}: {why}" for name, why in sorted(left_out.items())],
        "beyond_mesh": [f"{name}: up to {margin:.4g} NeRF units: {why}"
                        for name, (margin, why) in sorted(beyond_mesh.items())],
    }
