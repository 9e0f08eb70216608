"""Where the scene can be, from Blender's own geometry: the dataset's occupancy prior.

``datasets_gen`` voxelises the renderable geometry (after modifiers, in the NeRF frame, with
margins for hair and displacement) into ``occupancy_prior.npz``, named in
``scene_profile.json``. Its cells are marked conservatively: every cell a renderable
surface passes through, grown by a margin (``surface``), and optionally everything those
cells enclose (``solid``). Outside its box nothing renders.

A model's occupancy grid has other cells; ``allowed_cells`` marks each of them that
overlaps any marked prior cell, so nothing the prior holds is ever skipped.

Example:
    >>> import torch
    >>> prior = OccupancyPrior(torch.zeros(4, 4, 4, dtype=torch.bool), (0.0, 0.0, 0.0), 0.25, "surface")
    >>> prior.occupied[0, 1, 3] = True  # the cell [0, 0.25] × [0.25, 0.5] × [0.75, 1]
    >>> prior.allowed_cells((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2)).nonzero().tolist()
    [[0, 0, 1], [0, 1, 1]]
"""

from __future__ import annotations

import dataclasses
import json
import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from nerf_contract.dataset_layout import APPEARANCE_REGIONS, GEOMETRY_NAME, PROFILE_NAME

from ..core.display_colour import uniform_world_light
from ..core.errors import DatasetError
from ..core.mesh_normals import corner_normals, normal_volume, surface_cells
from ..core.mesh_shape import mesh_bodies, wall_share
from ..core.ply import read_face_materials, read_ply

PRIOR_KINDS = ("surface", "solid")
# Cells along the longest side of ``surface_grid``'s box.
SURFACE_GRID_RESOLUTION = 128
# A model cell whose edge lies within this fraction of a prior cell of a marked prior cell
# counts as overlapping it: float rounding never turns "touching" into "apart".
_TOUCH = 1e-6


@dataclass
class OccupancyPrior:
    """Marked cells ``occupied [nx, ny, nz]`` (cubes of side ``cell_size`` from ``box_min``)."""

    occupied: Tensor
    box_min: tuple[float, float, float]
    cell_size: float
    kind: str  # "surface" or "solid"
    # Cells every marked surface cell was grown by (the profile's margin): the surface itself
    # lies between this many and one more cells inside the marked region's boundary.
    margin_cells: int = 0
    # Beside a solid prior, its surface cells (the file holds both): with them the surface
    # field knows on which side of the surface each unmarked cell lies (surface_band.py).
    surface_cells: Tensor | None = None
    # What the surface in each cell is made of (uint8 ``[nx, ny, nz]``, an index of
    # ``APPEARANCE_REGIONS``; 0 where no surface was classified), from the scene's materials.
    regions: Tensor | None = None
    # The dataset's true surface (``scene_geometry.ply``), where it has one: its normals.
    geometry: Path | None = None
    # The scene's smooth glass: each material's IOR and colour by its index in the profile's
    # materials (``smooth_glass``; empty without any).
    glass_materials: dict[int, tuple[float, tuple[float, float, float]]] = field(default_factory=dict)
    # Whether every transmissive material is smooth glass (a geometry file without each face's
    # material then takes the transmissive cells' triangles as glass).
    all_transmissive_glass: bool = False
    # The world's light as a pixel shows it, where the world is one uniform colour
    # (``core.display_colour.uniform_world_light``): what the rays bent through glass start seeing.
    world_light: tuple[float, float, float] | None = None

    @property
    def box_max(self) -> tuple[float, float, float]:
        return tuple(lo + n * self.cell_size for lo, n in zip(self.box_min, self.occupied.shape))  # type: ignore[return-value]

    @property
    def bounds_the_surface(self) -> bool:
        """Whether it says on which side of the surface each cell lies: a solid prior that
        holds its surface cells, and some of them (``field_components/surface_band.py``)."""
        return self.kind == "solid" and self.surface_cells is not None and bool(self.surface_cells.any())

    @property
    def occupied_fraction(self) -> float:
        return float(self.occupied.float().mean())

    def allowed_cells(self, box_min: tuple[float, ...], box_max: tuple[float, ...], cells: tuple[int, int, int]) -> Tensor:
        """``[Gx, Gy, Gz]`` bool: the cells of a grid over ``[box_min, box_max]`` that overlap
        or touch a marked prior cell (closed cells: geometry on a shared face belongs to
        both). Cells outside the prior's box hold nothing."""
        return self._overlapping(self.occupied, box_min, box_max, cells)

    def region_cells(self, box_min: tuple[float, ...], box_max: tuple[float, ...], cells: tuple[int, int, int]) -> Tensor:
        """``[Gx, Gy, Gz]`` uint8: for each cell of a grid over ``[box_min, box_max]``, the
        region (an index of ``APPEARANCE_REGIONS``) of the prior cells it overlaps or touches,
        the latest where they differ: a cell that holds a diffuse and a glossy surface needs the
        glossy one's view dependence. 0 where it overlaps none; all 0 without ``regions``.

        Example:
            >>> import torch
            >>> prior = OccupancyPrior(torch.ones(2, 1, 1, dtype=torch.bool), (0.0, 0.0, 0.0), 1.0, "surface",
            ...                        regions=torch.tensor([1, 2], dtype=torch.uint8).view(2, 1, 1))
            >>> prior.region_cells((0.0, 0.0, 0.0), (2.0, 1.0, 1.0), (5, 1, 1)).view(-1).tolist()
            [1, 1, 2, 2, 2]
            >>> prior.region_cells((0.0, 0.0, 0.0), (2.0, 1.0, 1.0), (3, 1, 1)).view(-1).tolist()  # the middle one holds both
            [1, 2, 2]
        """
        out = torch.zeros(cells, dtype=torch.uint8)
        if self.regions is None:
            return out
        for region in range(1, len(APPEARANCE_REGIONS)):  # later regions overwrite earlier ones
            mask = self.regions == region
            if bool(mask.any()):
                out[self._overlapping(mask, box_min, box_max, cells)] = region
        return out

    def surface_grid(self, resolution: int = SURFACE_GRID_RESOLUTION) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """What the surface is made of and which way it faces, on a coarser grid over the
        prior's box (``resolution`` cubic cells along its longest side): ``regions`` uint8
        ``[nx, ny, nz]`` (``region_cells``), the true surface's ``normals`` ``[nx, ny, nz, 3]``
        (``core.mesh_normals``; zero without ``geometry``), and the grid's corners ``box_min``,
        ``box_max`` (``[3]`` each)."""
        low = np.asarray(self.box_min, np.float64)
        extent = np.asarray(self.box_max, np.float64) - low
        cell = float(extent.max()) / resolution
        shape = tuple(max(1, math.ceil(float(side) / cell - 1e-9)) for side in extent)
        high = low + cell * np.asarray(shape, np.float64)
        regions = self.region_cells(tuple(low.tolist()), tuple(high.tolist()), shape)  # type: ignore[arg-type]
        normals = np.zeros((*shape, 3), np.float32)
        if self.geometry is not None:
            vertices, faces = read_ply(self.geometry)
            if len(faces):
                normals = normal_volume(vertices, faces, corner_normals(vertices, faces), low, cell, shape)  # type: ignore[arg-type]
        return regions, torch.from_numpy(normals), torch.from_numpy(low).float(), torch.from_numpy(high).float()

    def glass_surfaces(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor] | None:
        """The true surface's triangles of smooth glass ``corners [T, 3, 3]``, their smooth
        normals at each corner ``[T, 3, 3]``, their IOR ``[T]``, which glass each is ``[T]``
        (an index of the next) and each glass's colour ``[M, 3]`` (``model_components.glass``);
        None without glass or geometry. Each triangle's material is in the geometry file
        (``read_face_materials``); in a file written before it, a triangle is glass where its
        corners and centre all lie in cells the prior says are transmissive, and only where
        every transmissive material is smooth glass, all of one IOR and colour."""
        found = self._glass_faces()
        if found is None:
            return None
        vertices, faces, material = found
        glass = material >= 0
        kinds = sorted(set(material[glass].tolist()))
        slot = np.searchsorted(np.asarray(kinds), material[glass])
        ior = np.asarray([self.glass_materials[k][0] for k in kinds])[slot]
        colours = torch.tensor([self.glass_materials[k][1] for k in kinds], dtype=torch.float32)
        normals = corner_normals(vertices, faces)[glass]
        return (torch.from_numpy(vertices[faces][glass]).float(), torch.from_numpy(normals).float(),
                torch.from_numpy(ior).float(), torch.from_numpy(slot).long(), colours)

    def without_glass(self) -> "OccupancyPrior":
        """This prior with the cells that hold glass and nothing else left empty: where
        rays are bent through the glass (``model_components.glass``) the field holds nothing
        at the glass, and density there would stand in the bent rays' way; cells within a
        cell of any other surface (the board a ball rests on) stay."""
        found = self._glass_faces()
        if found is None:
            return self
        vertices, faces, material = found
        corners, glass = vertices[faces], material >= 0
        low, shape = np.asarray(self.box_min), tuple(self.occupied.shape)
        grow = self.margin_cells + 1
        near_glass = surface_cells(corners[glass], low, self.cell_size, shape, grow)  # type: ignore[arg-type]
        near_other = surface_cells(corners[~glass], low, self.cell_size, shape, grow)  # type: ignore[arg-type]
        keep = torch.from_numpy(~(near_glass & ~near_other))
        return dataclasses.replace(self, occupied=self.occupied & keep,
                                   surface_cells=None if self.surface_cells is None else self.surface_cells & keep)

    def _glass_faces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The true surface's vertices and faces, and each face's glass material (its index in
        the profile's materials; -1 where it is not glass, or in a thin-walled body); None
        without glass or geometry."""
        return self._glass_record()[0]

    def thin_glass(self) -> dict[int, list[float]]:
        """The bodies of smooth glass left to the field because they are thin-walled: by their
        material's index in the profile's materials, each body's ``wall_share`` (under
        GLASS_MIN_WALL_SHARE)."""
        return dict(self._glass_record()[1])

    def _glass_record(self) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray] | None, dict[int, list[float]]]:
        """``_glass_faces`` and ``thin_glass``, read together once per question."""
        if not self.glass_materials or self.geometry is None:
            return None, {}
        # The plan, the model and its emptied cells each ask: the file is read once per question.
        key = (self.geometry, tuple(sorted(self.glass_materials.items())), self.all_transmissive_glass)
        cached = getattr(self, "_glass_cache", None)
        if cached is None or cached[0] != key:
            cached = (key, self._read_glass_faces())
            self._glass_cache = cached
        return cached[1]

    def _read_glass_faces(self) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray] | None, dict[int, list[float]]]:
        vertices, faces = read_ply(self.geometry)  # type: ignore[arg-type]
        if not len(faces):
            return None, {}
        materials = read_face_materials(self.geometry)  # type: ignore[arg-type]
        if materials is not None:
            material = np.where(np.isin(materials, list(self.glass_materials)), materials, -1)
        else:
            material = np.full(len(faces), -1)
            kinds = set(self.glass_materials.values())
            if self.regions is not None and self.all_transmissive_glass and len(kinds) == 1:
                material[self._in_transmissive_cells(vertices[faces])] = min(self.glass_materials)
        thin: dict[int, list[float]] = {}
        for kind in np.unique(material[material >= 0]).tolist():
            chosen = np.flatnonzero(material == kind)
            for body in mesh_bodies(vertices, faces[chosen]):
                share = wall_share(vertices[faces[chosen[body]]])
                if share < GLASS_MIN_WALL_SHARE:  # a shell of glass: left to the field, straight
                    material[chosen[body]] = -1
                    thin.setdefault(kind, []).append(share)
        return ((vertices, faces, material) if (material >= 0).any() else None), thin

    def _in_transmissive_cells(self, corners: np.ndarray) -> np.ndarray:
        """``[T]`` whether each triangle's corners and centre all lie in transmissive cells."""
        points = np.concatenate([corners, corners.mean(axis=1, keepdims=True)], axis=1)
        cells = np.floor((points - np.asarray(self.box_min)) / self.cell_size).astype(np.int64)
        shape = np.asarray(self.regions.shape)
        inside = ((cells >= 0) & (cells < shape)).all(axis=2)
        cells = np.clip(cells, 0, shape - 1)
        regions = self.regions.numpy()[cells[..., 0], cells[..., 1], cells[..., 2]]
        return (inside & (regions == APPEARANCE_REGIONS.index("transmissive"))).all(axis=1)

    def _overlapping(self, mask: Tensor, box_min: tuple[float, ...], box_max: tuple[float, ...],
                     cells: tuple[int, int, int]) -> Tensor:
        """``[Gx, Gy, Gz]`` bool: the grid's cells that overlap or touch a cell set in ``mask``
        (a bool array of the prior's shape)."""
        # A summed-volume table answers "any marked cell in this index box" in O(1) a cell.
        table = torch.zeros(tuple(n + 1 for n in mask.shape), dtype=torch.int64)
        table[1:, 1:, 1:] = mask.long().cumsum(0).cumsum(1).cumsum(2)
        ranges = []
        for axis in range(3):
            edges = torch.linspace(box_min[axis], box_max[axis], cells[axis] + 1, dtype=torch.float64)
            u = (edges - self.box_min[axis]) / self.cell_size  # model cell edges in prior cells
            n = mask.shape[axis]
            start = torch.floor(u[:-1] - _TOUCH).clamp(0, n).long()
            stop = torch.ceil(u[1:] + _TOUCH).clamp(0, n).long()
            ranges.append((start, stop))
        (x0, x1), (y0, y1), (z0, z1) = ranges
        X0, Y0, Z0 = torch.meshgrid(x0, y0, z0, indexing="ij")
        X1, Y1, Z1 = torch.meshgrid(x1, y1, z1, indexing="ij")
        count = (table[X1, Y1, Z1] - table[X0, Y1, Z1] - table[X1, Y0, Z1] - table[X1, Y1, Z0]
                 + table[X0, Y0, Z1] + table[X0, Y1, Z0] + table[X1, Y0, Z0] - table[X0, Y0, Z0])
        return count > 0


def load_occupancy_prior(dataset_dir: Path | str, kind: str) -> OccupancyPrior | None:
    """The dataset's prior of ``kind`` ("surface" or "solid"), or None when the dataset has
    none (datasets from other tools, or a Blender without numpy)."""
    if kind not in PRIOR_KINDS:
        raise ValueError(f"unknown occupancy prior {kind!r}; choose one of {', '.join(PRIOR_KINDS)}")
    profile_path = Path(dataset_dir) / PROFILE_NAME
    if not profile_path.is_file():
        return None
    try:
        profile = json.loads(profile_path.read_text())
        record = profile.get("occupancy_prior")
    except (json.JSONDecodeError, AttributeError, UnicodeDecodeError):
        return None  # the profile's own loader reports a broken profile
    if not isinstance(record, dict):
        return None
    name = record.get("file")
    if not isinstance(name, str) or Path(name).name != name:
        raise DatasetError(f"{profile_path}: 'occupancy_prior' 'file' must be a file name in the dataset folder, got {name!r}")
    path = Path(dataset_dir) / name
    if not path.is_file():
        raise DatasetError(f"{path}: occupancy prior not found (named in {profile_path.name})")
    try:
        with np.load(path, allow_pickle=False) as data:
            occupied = np.asarray(data[kind])
            surface_cells = np.asarray(data["surface"]) if kind == "solid" and "surface" in data.files else None
            regions = np.asarray(data["regions"]) if "regions" in data.files else None  # written since issue 60
            box_min = np.asarray(data["box_min"], dtype=np.float64)
            cell_size = float(np.asarray(data["cell_size"]))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
        raise DatasetError(f"{path}: not a readable occupancy prior ({exc})") from None
    if occupied.dtype != np.bool_ or occupied.ndim != 3 or min(occupied.shape) < 1:
        raise DatasetError(f"{path}: '{kind}' must be a 3-D bool array, got {occupied.dtype} {occupied.shape}")
    if surface_cells is not None and (surface_cells.dtype != np.bool_ or surface_cells.shape != occupied.shape):
        raise DatasetError(f"{path}: 'surface' must be a bool array of the shape of 'solid' {occupied.shape}, "
                           f"got {surface_cells.dtype} {surface_cells.shape}")
    if regions is not None:
        if regions.dtype != np.uint8 or regions.shape != occupied.shape:
            raise DatasetError(f"{path}: 'regions' must be a uint8 array of the shape of '{kind}' {occupied.shape}, "
                               f"got {regions.dtype} {regions.shape}")
        if int(regions.max(initial=0)) >= len(APPEARANCE_REGIONS):
            raise DatasetError(f"{path}: 'regions' holds {int(regions.max())}, not an index of the "
                               f"{len(APPEARANCE_REGIONS)} regions ({', '.join(APPEARANCE_REGIONS)})")
    if box_min.shape != (3,) or not np.isfinite(box_min).all() or not (math.isfinite(cell_size) and cell_size > 0):
        raise DatasetError(f"{path}: 'box_min' must be 3 finite numbers and 'cell_size' a positive number")
    margin = record.get("margin")
    margin_cells = margin.get("cells") if isinstance(margin, dict) else 0
    if not isinstance(margin_cells, int) or isinstance(margin_cells, bool) or margin_cells < 0:
        raise DatasetError(f"{profile_path}: 'occupancy_prior' 'margin' 'cells' must be a whole number of cells, "
                           f"got {margin_cells!r}")
    return OccupancyPrior(torch.from_numpy(occupied.copy()), tuple(box_min.tolist()), cell_size, kind,  # type: ignore[arg-type]
                          margin_cells, None if surface_cells is None else torch.from_numpy(surface_cells.copy()),
                          None if regions is None else torch.from_numpy(regions.copy()),
                          geometry if (geometry := Path(dataset_dir) / GEOMETRY_NAME).is_file() else None,
                          *_glass_facts(profile.get("materials")), uniform_world_light(profile.get("world")))


# Smooth glass: a material Blender renders as a smooth dielectric that lets (nearly) all light
# through, the kind whose rays ``model_components.glass`` bends (rough or partly transmissive
# glass scatters light the bent rays do not follow), nearly colourless: with its green cube
# (0.8, 0.95, 0.9) bent and tinted too, glass_and_gloss gained 0.60 dB over straight rays, against
# 0.81 with the cube left straight (docs/benchmarks.md, "Rays bent through glass"). The tint a
# colour this close to white gives is learned from it.
GLASS_MIN_TRANSMISSION = 0.9
GLASS_MAX_ROUGHNESS = 0.1
GLASS_MIN_COLOUR = 0.9


# Glass thinner than this (its mean chord 4V/S against its bounding box's diagonal: 0.385 for a
# ball or a cube, about 0.03 for a dish's walls) is left to the field with straight rays: through
# a thin wall a ray is only shifted, by under the wall's width, which a view-dependent colour
# learns, while its bent rays cannot show what Cycles shows at the glass's rims and silhouette.
# Measured at 100×100 after 120 s on 2 CPU cores: a glass dish with olives in it (walls 0.035 of
# 1.8 across) scored 32.78 dB straight against 25.72 bent; a ball on a checkerboard 33.06 bent
# against 27.23 straight (docs/benchmarks.md, "Rays bent through glass").
GLASS_MIN_WALL_SHARE = 0.1


def _glass_facts(materials) -> tuple[dict[int, tuple[float, tuple[float, float, float]]], bool]:
    """The profile's smooth glass materials' IOR and colour by index, and whether every
    transmissive material is smooth glass."""
    if not isinstance(materials, list):
        return {}, False
    transmissive = [(index, m) for index, m in enumerate(materials)
                    if isinstance(m, dict) and m.get("region") == "transmissive"]
    glass = {index: found for index, m in transmissive if (found := smooth_glass(m)) is not None}
    return glass, bool(transmissive) and len(glass) == len(transmissive)


def smooth_glass(material: dict) -> tuple[float, tuple[float, float, float]] | None:
    """A profile material's IOR and colour where it is smooth glass: transmissive, with constant
    inputs: transmission at least GLASS_MIN_TRANSMISSION, roughness at most GLASS_MAX_ROUGHNESS,
    a base colour of at least GLASS_MIN_COLOUR in each channel, metallic 0, alpha 1, and no other
    shader mixed in; else None. A profile written before the base colour was read has none. A
    volume inside (Volume Absorption: glass tinted by the depth a ray crosses) is not the glass
    ``model_components/glass.py`` traces: with its rays bent, glTF-Blender-IO's 16_volume.blend
    scored 30.73 dB at 100×100 after 120 s, against 38.71 with them straight (docs/benchmarks.md).

    Example:
        >>> glass = {"region": "transmissive", "appearance": {"inputs": {"transmission": {"value": 1.0},
        ...          "roughness": {"value": 0.0}, "metallic": {"value": 0.0}, "ior": {"value": 1.45},
        ...          "base_colour": {"value": [0.95, 1.0, 0.9]}}}}
        >>> smooth_glass(glass)
        (1.45, (0.95, 1.0, 0.9))
        >>> smooth_glass({"region": "transmissive", "appearance": {"inputs": {**glass["appearance"]["inputs"],
        ...              "roughness": {"value": 0.5}}}}) is None
        True
        >>> smooth_glass({"region": "transmissive", "appearance": {**glass["appearance"],
        ...              "other_shaders": ["volume 'Volume Absorption'"]}}) is None
        True
    """
    if not isinstance(material, dict) or material.get("region") != "transmissive":
        return None
    appearance = material.get("appearance") or {}
    if appearance.get("other_shaders"):
        return None
    inputs = appearance.get("inputs") or {}
    value = {name: (inputs.get(name) or {}).get("value", default)
             for name, default in (("transmission", None), ("roughness", 0.5), ("metallic", 0.0),
                                   ("alpha", 1.0), ("ior", None))}
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value.values()):
        return None
    colour = (inputs.get("base_colour") or {}).get("value")
    if not (isinstance(colour, list) and len(colour) == 3
            and all(isinstance(c, (int, float)) and not isinstance(c, bool) and GLASS_MIN_COLOUR <= c for c in colour)):
        return None
    if (value["transmission"] < GLASS_MIN_TRANSMISSION or value["roughness"] > GLASS_MAX_ROUGHNESS
            or value["metallic"] != 0 or value["alpha"] < 1 or not 1.0 < value["ior"] < 4.0):
        return None
    return float(value["ior"]), tuple(min(float(c), 1.0) for c in colour)  # type: ignore[return-value]
