"""The occupancy prior: conservative by construction (pure maths against an exact triangle/box
test) and in practice (real scenes against Blender's own ray casts); Blender 3.4 without numpy
writes none and says why.  Resume, shards and merge keep it: tests/test_datasets_gen_runs.py.
"""

from __future__ import annotations

import doctest
import json
import math
import subprocess
import sys
from collections import deque
from pathlib import Path

import numpy as np
import pytest
import torch
from test_datasets_gen import REPO, SCRIPTS, load_split, require_blender, run_module

from datasets_gen.core import voxelise as vx
from datasets_gen.core.voxelise import Grid, Part, box_triangles, dilate, mark_boxes, mark_triangles, outside, voxelise
from nerf_backend.field_components.surface_band import SignedDistanceBounds

TINY = ["--resolution", "24", "--train-views", "2", "--val-views", "1", "--test-views", "1", "--samples", "1",
        "--no-progress"]


# --- exact reference: does a triangle touch a box (closed sets)? -------------------------------


def touches(triangle: np.ndarray, lows: np.ndarray, highs: np.ndarray) -> np.ndarray:
    """[N] bool: the triangle and each closed box [lows, highs] share a point (separating axes:
    the 3 box normals, the triangle's normal, the 9 edge x box-axis products; a zero axis, from a
    degenerate triangle, separates nothing, and for a segment or point the others suffice)."""
    centres, halves = (lows + highs) / 2.0, (highs - lows) / 2.0
    corners = triangle[None, :, :] - centres[:, None, :]
    edges = [triangle[1] - triangle[0], triangle[2] - triangle[1], triangle[0] - triangle[2]]
    axes = list(np.eye(3)) + [np.cross(edges[0], edges[1])]
    axes += [np.cross(edge, axis) for edge in edges for axis in np.eye(3)]
    separated = np.zeros(len(lows), bool)
    for axis in axes:
        if not np.any(axis):
            continue
        projected = corners @ axis
        radius = halves @ np.abs(axis)
        separated |= (projected.min(axis=1) > radius) | (projected.max(axis=1) < -radius)
    return ~separated


def touched_cells(triangle: np.ndarray, grid: Grid, grow_cells: int = 0) -> np.ndarray:
    """[nx, ny, nz] bool: the cells (each grown by `grow_cells` cells) that the triangle touches;
    only cells near the triangle's bounds are tested (the others cannot touch it)."""
    first = np.floor((triangle.min(axis=0) - grid.box_min) / grid.cell_size).astype(int) - 2 - grow_cells
    last = np.floor((triangle.max(axis=0) - grid.box_min) / grid.cell_size).astype(int) + 2 + grow_cells
    first, last = np.maximum(first, 0), np.minimum(last, np.array(grid.shape) - 1)
    ranges = [np.arange(first[axis], last[axis] + 1) for axis in range(3)]
    indices = np.stack(np.meshgrid(*ranges, indexing="ij"), -1).reshape(-1, 3)
    lows = grid.box_min + grid.cell_size * (indices - grow_cells)
    result = np.zeros(grid.shape, bool)
    result[tuple(indices.T)] = touches(triangle, lows, lows + grid.cell_size * (1 + 2 * grow_cells))
    return result


def cell_boxes(grid: Grid, grow_cells: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indices [N, 3], lows, highs) of every cell, each grown by `grow_cells` cells."""
    indices = np.argwhere(np.ones(grid.shape, bool))
    lows = grid.box_min + grid.cell_size * (indices - grow_cells)
    return indices, lows, lows + grid.cell_size * (1 + 2 * grow_cells)


def random_triangles(rng: np.random.Generator, span: float) -> np.ndarray:
    """General, sliver, long-thin, lattice (through cell corners and edges), face-aligned and
    degenerate (collinear, coincident, point) triangles inside [0, span]^3 (cells of size 1)."""
    def points(count: int) -> np.ndarray:
        return rng.uniform(0.0, span, (count, 3))

    def lattice(count: int, step: float = 1.0) -> np.ndarray:
        return rng.integers(0, int(span / step) + 1, (count, 3)) * step

    triangles = [np.stack([points(1)[0], points(1)[0], points(1)[0]]) for _ in range(60)]
    for _ in range(40):  # slivers: the third corner a hair's breadth off the first edge
        a, b = points(2)
        offset = rng.normal(size=3) * 10.0 ** rng.uniform(-9, -3)
        triangles.append(np.stack([a, b, a + rng.uniform() * (b - a) + offset]))
    for _ in range(30):  # long and thin, across the grid
        a = points(1)[0]
        b = np.clip(a + rng.normal(size=3) * span, 0.0, span)
        triangles.append(np.stack([a, b, a + rng.normal(size=3) * 0.05]))
    triangles += [lattice(3) for _ in range(40)] + [lattice(3, 0.5) for _ in range(30)]
    for _ in range(20):  # in a cell face's plane
        triangle = lattice(3, 0.5)
        triangle[:, rng.integers(3)] = rng.integers(0, int(span) + 1)
        triangles.append(triangle)
    for _ in range(20):  # collinear, through corners
        a, b = lattice(2)
        triangles.append(np.stack([a, b, a + rng.choice([0.25, 0.5, 1.0]) * (b - a)]))
    triangles += [np.repeat(lattice(1), 3, axis=0) for _ in range(15)]  # a point on a corner
    triangles += [np.repeat(points(1), 3, axis=0) for _ in range(5)]
    for _ in range(20):  # smaller than a cell, at a corner
        corner = lattice(1)[0]
        triangles.append(corner + rng.uniform(-0.2, 0.2, (3, 3)))
    return np.clip(np.array(triangles), 0.0, span)


GRIDS = {
    "unit cells on integers": (np.array([-2.0, -2.0, -2.0]), 1.0),
    "odd cells at odd offsets": (np.array([-1.31, -0.77, -2.03]), 0.37),
}


@pytest.mark.parametrize("grid_name", sorted(GRIDS))
def test_every_cell_a_triangle_touches_is_marked_and_no_cell_farther(grid_name: str) -> None:
    box_min, cell_size = GRIDS[grid_name]
    span = 10.0
    grid = Grid(box_min, cell_size, (14, 14, 14) if cell_size == 1.0 else (15, 14, 17))
    triangles = random_triangles(np.random.default_rng(7), span) * cell_size
    for triangle in triangles:
        marked = np.zeros(grid.shape, bool)
        mark_triangles(marked, grid, triangle[None])
        covered = dilate(marked, 1)
        assert not (touched_cells(triangle, grid) & ~covered).any(), f"missed cells of {triangle.tolist()}"
        # Tight: a covered cell is at most one cell from the triangle (its box grown by a cell touches it).
        assert not (covered & ~touched_cells(triangle, grid, 1)).any(), f"cells too far from {triangle.tolist()}"


def test_voxelise_covers_every_touched_cell_with_its_own_grid() -> None:
    rng = np.random.default_rng(11)
    triangles = random_triangles(rng, 3.0) * 0.7 + np.array([0.3, -1.0, 2.0])
    prior = voxelise([Part(triangles)], resolution=48, base_margin_cells=0)
    grid = prior.grid
    assert grid.shape[int(np.argmax(np.ptp(triangles.reshape(-1, 3), axis=0)))] == 48
    np.testing.assert_allclose(grid.box_max, grid.box_min + grid.cell_size * np.array(grid.shape))
    for triangle in triangles[::4]:  # every kind, a quarter of each (the SAT over many cells is slow)
        assert not (touched_cells(triangle, grid) & ~prior.surface).any()


def chebyshev_ball(shape: tuple[int, int, int], centre: np.ndarray, radius: int) -> np.ndarray:
    indices = np.indices(shape).reshape(3, -1).T
    return (np.abs(indices - centre).max(axis=1) <= radius).reshape(shape)


@pytest.mark.parametrize("cells", [0, 1, 2, 3, 5, 8])
def test_dilation_is_exactly_a_cube_of_the_margin(cells: int) -> None:
    for centre in (np.array([9, 9, 9]), np.array([1, 17, 4])):  # inside; clipped at the border
        marked = np.zeros((19, 19, 19), bool)
        marked[tuple(centre)] = True
        np.testing.assert_array_equal(dilate(marked, cells), chebyshev_ball(marked.shape, centre, cells))


@pytest.mark.parametrize(("base", "margin"), [(0, 0.0), (1, 0.0), (1, 0.25), (3, 0.1)])
def test_voxelise_margin_grows_exactly_as_stated(base: int, margin: float) -> None:
    """A point grows into a cube of 1 (sampling) + base + ceil(margin / cell) cells; a part
    without margin beside it does not grow with it."""
    point = np.full((1, 3, 3), 0.5)
    segment = np.array([[[3.0, 0.5, 0.5], [4.0, 0.5, 0.5], [4.0, 0.5, 0.5]]])
    prior = voxelise([Part(point, margin=margin), Part(segment)], resolution=64, base_margin_cells=base)
    grid = prior.grid
    point_cell = grid.cell_of(point[0, :1])[0]
    reach = 1 + base + vx.margin_in_cells(margin, grid.cell_size)
    ball = chebyshev_ball(grid.shape, point_cell, reach)
    segment_marks = np.zeros(grid.shape, bool)
    mark_triangles(segment_marks, grid, segment)
    expected = ball | dilate(segment_marks, 1 + base)
    np.testing.assert_array_equal(prior.surface, expected)
    if margin:
        assert reach * grid.cell_size >= margin + (1 + base) * grid.cell_size


def test_closed_box_solid_holds_its_interior_and_surface_stays_near_it() -> None:
    low, high = np.array([0.2, 0.3, 0.1]), np.array([1.9, 1.2, 1.4])
    triangles = box_triangles(low, high)
    base = 1
    prior = voxelise([Part(triangles)], resolution=64, base_margin_cells=base)
    grid, surface, solid = prior.grid, prior.surface, prior.solid
    assert (grid.box_min < low).all() and (grid.box_max > high).all()
    for axis in range(3):  # the outer layer is empty: outside the box nothing renders
        assert not surface.take([0, -1], axis=axis).any()
    _, lows, highs = cell_boxes(grid)
    interior = ((lows > low) & (highs < high)).all(axis=1).reshape(grid.shape)
    assert interior.sum() > 1000 and (solid | ~interior).all()
    assert (surface | solid == solid).all()
    assert (solid & ~surface).sum() > 0.4 * interior.sum()  # the flood fill did fill it
    # No surface cell farther than 1 + margin cells from a triangle.
    near = np.zeros(grid.shape, bool)
    for triangle in triangles:
        near |= touched_cells(triangle, grid, 1 + base)
    assert not (surface & ~near).any()
    # Nothing outside the box mesh (grown by the margin and a cell) is solid.
    reach = (2 + base) * grid.cell_size
    outer = ((highs < low - reach) | (lows > high + reach)).any(axis=1).reshape(grid.shape)
    assert not (solid & outer).any()


def test_each_surface_cell_holds_the_region_of_the_parts_that_mark_it() -> None:
    """Two boxes of other materials that overlap, one with a margin: every cell a part marks
    (dilated as the surface is) holds its region, a cell both mark the later region of
    APPEARANCE_REGIONS, and no cell off the surface holds any."""
    from nerf_contract.dataset_layout import APPEARANCE_REGIONS
    diffuse, glass = APPEARANCE_REGIONS.index("diffuse"), APPEARANCE_REGIONS.index("transmissive")
    clay = Part(box_triangles([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]), region=diffuse)
    vase = Part(box_triangles([0.7, 0.2, 0.2], [1.6, 0.8, 0.9]), margin=0.05, region=glass)
    prior = voxelise([clay, vase], resolution=48)
    grid = prior.grid

    def own_cells(part: Part) -> np.ndarray:  # the part's marks on the prior's grid, dilated as voxelise does
        marked = np.zeros(grid.shape, bool)
        mark_triangles(marked, grid, part.triangles)
        return dilate(marked, 1 + vx.BASE_MARGIN_CELLS + vx.margin_in_cells(part.margin, grid.cell_size))

    clay_cells, vase_cells = own_cells(clay), own_cells(vase)
    assert prior.regions.dtype == np.uint8 and np.array_equal(prior.surface, clay_cells | vase_cells)
    assert (clay_cells & vase_cells).sum() > 0 and (clay_cells & ~vase_cells).sum() > 100
    assert (prior.regions[vase_cells] == glass).all()  # the shared cells included
    assert (prior.regions[clay_cells & ~vase_cells] == diffuse).all()
    assert not prior.regions[~prior.surface].any()


def test_filled_boxes_cover_every_cell_they_touch() -> None:
    rng = np.random.default_rng(3)
    grid = Grid(np.zeros(3), 0.5, (16, 16, 16))
    _, lows, highs = cell_boxes(grid)
    for _ in range(50):
        corners = np.sort(rng.integers(2, 28, (2, 3)) / 4.0, axis=0)  # often on cell faces
        marked = np.zeros(grid.shape, bool)
        mark_boxes(marked, grid, corners[None])
        touching = ((lows <= corners[1]) & (highs >= corners[0])).all(axis=1).reshape(grid.shape)
        assert not (touching & ~dilate(marked, 1)).any()


def flood_reference(surface: np.ndarray) -> np.ndarray:
    """Breadth-first flood fill from every unmarked border cell (6-connected)."""
    reached = np.zeros_like(surface)
    queue = deque()
    for index in np.argwhere(~surface):
        if (index == 0).any() or (index == np.array(surface.shape) - 1).any():
            reached[tuple(index)] = True
            queue.append(tuple(index))
    while queue:
        cell = queue.popleft()
        for axis in range(3):
            for step in (-1, 1):
                other = list(cell)
                other[axis] += step
                if 0 <= other[axis] < surface.shape[axis] and not surface[tuple(other)] and not reached[tuple(other)]:
                    reached[tuple(other)] = True
                    queue.append(tuple(other))
    return reached


@pytest.mark.parametrize("density", [0.15, 0.3, 0.45, 0.6])
def test_scan_line_flood_fill_equals_breadth_first_search(density: float) -> None:
    rng = np.random.default_rng(int(density * 100))
    for _ in range(3):
        surface = rng.random((9, 12, 10)) < density
        np.testing.assert_array_equal(outside(surface), flood_reference(surface))
    spiral = np.ones((15, 15, 3), bool)  # a winding corridor: many turns
    spiral[1:-1, 1:-1, 1] = False
    for row in range(2, 13, 2):
        spiral[row, (1 if row % 4 else 2):(13 if row % 4 else 14), 1] = True
    np.testing.assert_array_equal(outside(spiral), flood_reference(spiral))


def test_voxelise_examples() -> None:
    result = doctest.testmod(vx)
    assert result.attempted > 10 and result.failed == 0


def test_nothing_to_voxelise_is_an_error() -> None:
    with pytest.raises(ValueError, match="no renderable geometry"):
        voxelise([Part(np.zeros((0, 3, 3)))])
    with pytest.raises(ValueError, match="no extent"):
        voxelise([Part(np.ones((1, 3, 3)))])


# --- real scenes against Blender's ray casts ----------------------------------------------------


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory, shared_scenes: Path) -> dict[str, Path]:
    """name -> .blend: the two real shared scenes and make_scenes' occupancy scene."""
    out = tmp_path_factory.mktemp("occupancy_scenes")
    result = subprocess.run([sys.executable, str(SCRIPTS / "make_scenes.py"), str(out), "occupancy"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return {"A": shared_scenes / "A.blend", "RobotExpressive": shared_scenes / "RobotExpressive.blend",
            "occupancy": out / "occupancy.blend"}


@pytest.fixture(scope="module")
def datasets(scenes: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("occupancy_datasets")
    made = {}
    for name, blend in scenes.items():
        extra = ["--allow-missing"] if name == "RobotExpressive" else []  # its texture is missing
        result = run_module(str(blend), "--out", str(out / name), *TINY, *extra)
        assert result.returncode == 0, result.stderr
        assert "occupancy prior:" in result.stderr
        made[name] = out / name
    return made


def load_prior(dataset: Path) -> tuple[dict, dict[str, np.ndarray]]:
    profile = json.loads((dataset / "scene_profile.json").read_text())
    with np.load(dataset / profile["occupancy_prior"]["file"]) as data:
        arrays = {key: data[key] for key in data.files}
    return profile, arrays


def marked(arrays: dict[str, np.ndarray], kind: str, points: np.ndarray) -> np.ndarray:
    """[N] bool: each NeRF-frame point lies in a marked cell (outside the box: empty)."""
    grid = arrays[kind]
    cells = np.floor((points - arrays["box_min"]) / arrays["cell_size"]).astype(int)
    inside = ((cells >= 0) & (cells < np.array(grid.shape))).all(axis=1)
    result = np.zeros(len(points), bool)
    result[inside] = grid[tuple(cells[inside].T)]
    return result


def to_nerf(profile: dict, points: np.ndarray) -> np.ndarray:
    matrix = np.array(profile["world_to_nerf"]["matrix"])
    return points @ matrix[:3, :3].T + matrix[:3, 3]


# Measured at 256 cells (the default): surface / solid fractions of the grid's box.
MEASURED = {"A": (0.056, 0.124), "RobotExpressive": (0.080, 0.126), "occupancy": (0.151, 0.173)}


@pytest.mark.parametrize("name", sorted(MEASURED))
def test_every_blender_ray_hit_lies_in_a_marked_cell(name: str, scenes: dict[str, Path],
                                                     datasets: dict[str, Path], tmp_path: Path) -> None:
    dataset = datasets[name]
    profile, arrays = load_prior(dataset)
    record = profile["occupancy_prior"]
    # The npz and its profile record agree.
    assert list(arrays["surface"].shape) == record["resolution"] == list(arrays["solid"].shape)
    assert max(record["resolution"]) == 256 and arrays["surface"].dtype == bool
    np.testing.assert_array_equal(arrays["box_min"], record["box_min"])
    np.testing.assert_array_equal(arrays["box_max"], record["box_max"])
    np.testing.assert_allclose(arrays["box_max"], arrays["box_min"] + record["cell_size"] * np.array(record["resolution"]))
    assert float(arrays["cell_size"]) == record["cell_size"]
    assert record["surface_fraction"] == pytest.approx(arrays["surface"].mean())
    assert record["solid_fraction"] == pytest.approx(arrays["solid"].mean())
    assert (arrays["solid"] | arrays["surface"] == arrays["solid"]).all()
    assert load_split(dataset, "train")["world_to_nerf"] == profile["world_to_nerf"]

    hits_file = tmp_path / "hits.json"
    result = subprocess.run([sys.executable, str(SCRIPTS / "ray_hits.py"), str(scenes[name]), str(hits_file),
                             "4000", "5"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    hits = json.loads(hits_file.read_text())
    assert set(hits["objects"]) <= set(profile["objects"])
    points = to_nerf(profile, np.array(hits["hits"]))
    assert len(points) > 1500
    for kind in ("surface", "solid"):
        missed = points[~marked(arrays, kind, points)]
        assert len(missed) == 0, f"{len(missed)} of {len(points)} hits outside '{kind}': {missed[:5].tolist()}"
    # Every hit lies in the band the surface field is kept within (the surface cells less
    # the margin): neither side's bound excludes it.
    band = SignedDistanceBounds(arrays["surface"], arrays["solid"], tuple(arrays["box_min"]), float(arrays["cell_size"]),
                                record["margin"]["cells"])
    lower, upper = band(torch.from_numpy(points))
    assert float(lower.max()) <= 0.0 <= float(upper.min()), "a Blender ray hit outside the surface band"
    # Tight enough to skip most of the box (measured: MEASURED above).
    surface_fraction, solid_fraction = MEASURED[name]
    assert record["surface_fraction"] == pytest.approx(surface_fraction, abs=0.01)
    assert record["solid_fraction"] == pytest.approx(solid_fraction, abs=0.01)
    assert record["surface_fraction"] < 0.2


def test_hair_displacement_and_unmeasurable_objects_get_their_margins(datasets: dict[str, Path]) -> None:
    profile, arrays = load_prior(datasets["occupancy"])
    record = profile["occupancy_prior"]
    scale, cell = profile["world_to_nerf"]["scale"], record["cell_size"]
    reasons = record["margin"]["reasons"]
    assert record["margin"]["cells"] == 1 and any(reason.startswith("motion: none") for reason in reasons)
    hair_cells, displacement_cells = math.ceil(0.5 * scale / cell), math.ceil(0.3 * scale / cell)
    assert any(reason.startswith(f"Hairy: +{hair_cells} cells") and "hair length 0.5" in reason for reason in reasons)
    assert any(reason.startswith(f"Displaced: +{displacement_cells} cells") and "scale 0.3" in reason
               for reason in reasons)
    assert [entry.split(":")[0] for entry in record["filled_boxes"]] == ["Strands", "Unreadable"]
    # The scene geometry file holds the meshes only: it names what it leaves out and what
    # renders beyond its mesh.
    geometry = profile["geometry"]
    assert [entry.split(":")[0] for entry in geometry["left_out"]] == ["Strands", "Unreadable"]
    assert [entry.split(":")[0] for entry in geometry["beyond_mesh"]] == ["Displaced", "Hairy"]

    def is_marked(*blender_points: tuple[float, float, float]) -> list[bool]:
        return marked(arrays, "surface", to_nerf(profile, np.array(blender_points))).tolist()

    # Hair 0.5 long on a ball of radius 0.4 at x = 2.5: marked up to its tips, not far beyond them.
    assert is_marked((2.5 + 0.4 + 0.48, 0.0, 0.0), (2.5, 0.0, 0.4 + 0.48)) == [True, True]
    assert is_marked((2.5 + 0.4 + 0.5 + 6 * cell / scale, 0.0, 0.0)) == [False]
    # Displacement 0.3 (midlevel 0.5, height in [0, 1]): marked within 0.3, not at 0.45.
    assert is_marked((-2.5 - 0.4 - 0.28, 0.0, 0.0), (-2.5 - 0.4 - 0.45, 0.0, 0.0)) == [True, False]
    # Hair curves: their whole bounding box (x 0..0.2, z -0.5..0.5 at y = -2.5) is filled.
    grid = np.stack(np.meshgrid(np.linspace(0.0, 0.2, 5), [-2.5], np.linspace(-0.5, 0.5, 9)), -1).reshape(-1, 3)
    assert all(is_marked(*map(tuple, grid)))
    # The unreadable displacement fills the ball's box grown by 10 % of its size (0.06).
    assert is_marked((0.0, 2.5 + 0.3 + 0.05, 0.0), (0.29, 2.79, 0.29)) == [True, True]


@pytest.mark.blender_binary
def test_blender_without_numpy_writes_a_complete_dataset_without_a_prior(tmp_path: Path,
                                                                         shared_scenes: Path) -> None:
    blender = require_blender()
    out = tmp_path / "dataset"
    result = subprocess.run(
        [blender, "-b", str(shared_scenes / "A.blend"), "--python", str(REPO / "datasets_gen" / "generate.py"),
         "--", "--out", str(out), *TINY], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert "datasets_gen: note: no occupancy prior: this Blender's Python has no numpy" in result.stderr
    profile = json.loads((out / "scene_profile.json").read_text())
    assert profile["occupancy_prior"] is None
    assert profile["occupancy_prior_reason"] == "this Blender's Python has no numpy"
    assert not (out / "occupancy_prior.npz").exists()
    assert profile["geometry"] is None and profile["geometry_reason"] == "this Blender's Python has no numpy"
    assert not (out / "scene_geometry.ply").exists()
    for split in ("train", "val", "test"):
        for frame in load_split(out, split)["frames"]:
            assert (out / (frame["file_path"] + ".png")).is_file()
