"""PLY mesh files read as arrays: the true surface ``datasets_gen`` writes
(``scene_geometry.ply``, binary little-endian) and meshes from other tools (ASCII or binary).

Only what a surface needs is read: the vertices' ``x, y, z`` and each face's corner list
(polygons split into triangle fans); other properties are skipped. Anything else (no vertices,
a face element with more than its corner list in a binary file, a malformed body) is a
``NerfError`` naming the file.

Example:
    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "quad.ply"
    >>> _ = path.write_text("ply\\nformat ascii 1.0\\nelement vertex 4\\nproperty float x\\nproperty float y\\n"
    ...                     "property float z\\nelement face 1\\nproperty list uchar int vertex_indices\\nend_header\\n"
    ...                     "0 0 0\\n1 0 0\\n1 1 0\\n0 1 0\\n4 0 1 2 3\\n")
    >>> vertices, triangles = read_ply(path)
    >>> vertices.shape, triangles.tolist()
    ((4, 3), [[0, 1, 2], [0, 2, 3]])
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import NerfError

SCALARS = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
           "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
           "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
ENDIAN = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "="}


@dataclass
class _Element:
    name: str
    count: int
    scalars: list[tuple[str, str]] = field(default_factory=list)  # (name, numpy type)
    lists: list[tuple[str, str, str]] = field(default_factory=list)  # (name, count type, item type)


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [V, 3] float64, triangles [F, 3] int64) of the PLY file at ``path``."""
    vertices, faces, _ = _read(Path(path))
    return vertices, faces


def read_face_materials(path: Path) -> np.ndarray | None:
    """Each triangle's material ``[F]`` int64 (an index into the scene profile's materials) where
    the file has ``datasets_gen``'s ``face_material`` element beside triangles alone; else None
    (a file written before it, or another tool's)."""
    _, faces, tables = _read(Path(path))
    table = tables.get("face_material")
    if table is None or "material" not in (table.dtype.names or ()) or len(table) != len(faces):
        return None
    return table["material"].astype(np.int64)


def _read(path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """``read_ply``'s arrays, and the tables of a binary file's other elements of scalars alone."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise NerfError(f"{path}: cannot read the mesh ({exc.strerror or exc})") from None
    fmt, elements, body = _header(path, data)
    tables: dict[str, np.ndarray] = {}
    try:
        if fmt == "ascii":
            vertices, faces = _ascii_body(elements, body)
        else:
            vertices, faces = _binary_body(path, elements, body, ENDIAN[fmt], tables)
    except (ValueError, IndexError) as exc:
        raise NerfError(f"{path}: not a readable PLY mesh: {exc}") from None
    if len(vertices) and len(faces) and not 0 <= faces.min() <= faces.max() < len(vertices):
        raise NerfError(f"{path}: a face names a vertex that is not there")
    return vertices, faces, tables


def _header(path: Path, data: bytes) -> tuple[str, list[_Element], bytes]:
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise NerfError(f"{path}: not a PLY file (no 'ply' ... 'end_header')")
    body = data[data.index(b"\n", end) + 1:] if b"\n" in data[end:] else b""
    fmt, elements = None, []
    for line in data[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3 and words[1] in ENDIAN:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append(_Element(words[1], int(words[2])))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list" \
                and words[2] in SCALARS and words[3] in SCALARS:
            elements[-1].lists.append((words[4], SCALARS[words[2]], SCALARS[words[3]]))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in SCALARS:
            elements[-1].scalars.append((words[2], SCALARS[words[1]]))
        else:
            raise NerfError(f"{path}: PLY header line not understood: {line.strip()!r}")
    vertex = next((e for e in elements if e.name == "vertex"), None)
    if fmt is None or vertex is None or not {"x", "y", "z"} <= {name for name, _ in vertex.scalars}:
        raise NerfError(f"{path}: a PLY mesh needs a format line and vertices with x, y and z")
    return fmt, elements, body


def _fans(polygons: list[list[int]]) -> np.ndarray:
    """Each polygon's triangle fan, [F, 3]."""
    triangles = [(p[0], p[k], p[k + 1]) for p in polygons for k in range(1, len(p) - 1)]
    return np.array(triangles, dtype=np.int64).reshape(-1, 3)


def _ascii_body(elements: list[_Element], body: bytes) -> tuple[np.ndarray, np.ndarray]:
    lines = iter(body.decode("ascii").splitlines())
    vertices, polygons = np.zeros((0, 3)), []
    for element in elements:
        rows = [next(lines).split() for _ in range(element.count)]
        if element.name == "vertex":
            names = [name for name, _ in element.scalars]
            columns = [names.index(axis) for axis in "xyz"]
            vertices = np.array([[float(row[c]) for c in columns] for row in rows]).reshape(-1, 3)
        elif element.name == "face":
            # The corner list: after the face's scalar properties, if it has any before it.
            start = len(element.scalars)
            polygons = [[int(v) for v in row[start + 1:start + 1 + int(row[start])]] for row in rows]
    return vertices, _fans(polygons)


def _binary_body(path: Path, elements: list[_Element], body: bytes, endian: str,
                 tables: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    offset, vertices, faces = 0, np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    for element in elements:
        if element.lists and (element.name != "face" or element.scalars or len(element.lists) > 1):
            raise NerfError(f"{path}: binary PLY element {element.name!r} has lists this reader cannot skip "
                            "(it reads vertices and faces holding only their corner lists)")
        if element.name == "face":
            _, count_type, index_type = element.lists[0]
            faces, offset = _binary_faces(body, offset, element.count, endian + count_type, endian + index_type)
            continue
        dtype = np.dtype([(name, endian + kind) for name, kind in element.scalars])
        table = np.frombuffer(body, dtype=dtype, count=element.count, offset=offset)
        offset += dtype.itemsize * element.count
        tables[element.name] = table
        if element.name == "vertex":
            vertices = np.stack([table[axis].astype(np.float64) for axis in "xyz"], axis=1)
    return vertices, faces


def _binary_faces(body: bytes, offset: int, count: int, count_type: str, index_type: str) -> tuple[np.ndarray, int]:
    """Faces that are all triangles in one read; others corner list by corner list."""
    triangles = np.dtype([("count", count_type), ("indices", index_type, (3,))])
    if len(body) - offset >= triangles.itemsize * count:
        table = np.frombuffer(body, dtype=triangles, count=count, offset=offset)
        if (table["count"] == 3).all():
            return table["indices"].astype(np.int64), offset + triangles.itemsize * count
    polygons = []
    size, item = np.dtype(count_type).itemsize, np.dtype(index_type)
    for _ in range(count):
        corners = int(np.frombuffer(body, dtype=count_type, count=1, offset=offset)[0])
        polygons.append(np.frombuffer(body, dtype=item, count=corners, offset=offset + size).tolist())
        offset += size + corners * item.itemsize
    return _fans(polygons), offset
