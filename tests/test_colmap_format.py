"""--format colmap: a COLMAP model of the training views, read back by a real reader (pycolmap),
checked against the renders, the nerf_synthetic JSON and Cycles' own depth pass.

The maths first (quaternions and poses against pycolmap's and 3DGS's conventions, the depth
buffer against analytic surfaces, the PNG reader against Pillow for every row filter), then a
real dataset of a scene nobody here made (../shared/scenes/A.blend) rendered by datasets_gen.
"""

from __future__ import annotations

import io
import json
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image
from test_datasets_gen import DEMO_ARGS, REPO, load_split, read_exr, require_blender, run_module

from datasets_gen.core.options import DatasetGenError
from datasets_gen.core.zbuffer import GRAZING_COS, PinholeCamera, depth_buffer, points_seen, project
from datasets_gen.io.colmap_export import write_colmap
from datasets_gen.io.colmap_model import quaternion, sample_surface, world_to_camera
from datasets_gen.io.png_image import png_bytes, read_png
from datasets_gen.io.surface_mesh import read_ply

SCENE = REPO.parent / "shared" / "scenes" / "A.blend"
# A non-square image, so that x and y conventions cannot be swapped unnoticed.
WIDTH, HEIGHT = 160, 120
TRAIN_VIEWS = 16


def random_rotations(count: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(count, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.array([pycolmap.Rotation3d(np.array([x, y, z, w])).matrix() for w, x, y, z in q])


# --- the maths ------------------------------------------------------------------------------------


def test_quaternions_are_colmaps():
    """(w, x, y, z) with w >= 0, the rotation pycolmap builds from them (to 1e-12)."""
    for rotation in random_rotations(200):
        w, x, y, z = quaternion(rotation)
        assert w >= 0
        np.testing.assert_allclose(pycolmap.Rotation3d(np.array([x, y, z, w])).matrix(), rotation, atol=1e-12)
    half_turns = [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]  # w = 0: the trap
    for rotation in half_turns:
        w, x, y, z = quaternion(rotation)
        np.testing.assert_allclose(pycolmap.Rotation3d(np.array([x, y, z, w])).matrix(), rotation, atol=1e-12)


def test_poses_follow_the_3dgs_conversion_of_nerf_synthetic():
    """world_to_camera equals what 3D Gaussian Splatting's nerf_synthetic reader computes
    (flip the camera's y and z, invert), and the camera centre is kept."""
    rng = np.random.default_rng(1)
    for rotation in random_rotations(50, seed=2):
        camera_to_world = np.eye(4)
        camera_to_world[:3, :3], camera_to_world[:3, 3] = rotation, rng.normal(size=3) * 4
        flipped = camera_to_world.copy()
        flipped[:3, 1:3] *= -1
        expected = np.linalg.inv(flipped)
        r, t = world_to_camera(camera_to_world.tolist())
        np.testing.assert_allclose(r, expected[:3, :3], atol=1e-12)
        np.testing.assert_allclose(t, expected[:3, 3], atol=1e-12)
        np.testing.assert_allclose(-r.T @ t, camera_to_world[:3, 3], atol=1e-12)


def uv_sphere(radius: float, rings: int, segments: int) -> tuple[np.ndarray, np.ndarray]:
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    vertices = radius * np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    faces = []
    for i in range(rings):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            faces += [[a, c, d], [a, d, b]]
    return vertices, np.array(faces)


def pixel_rays(camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel centre: the ray direction with z = 1 (camera frame)."""
    j, i = np.mgrid[0:camera.height, 0:camera.width]
    return (i + 0.5 - camera.cx) / camera.fx, (j + 0.5 - camera.cy) / camera.fy


def test_depth_buffer_of_a_sphere_is_the_analytic_one():
    """A finely tessellated sphere of radius 1, 4 units ahead: its depth at each pixel centre is
    the ray-sphere intersection to the tessellation's sagitta (5e-4 here), and it covers exactly
    the pixels whose rays meet the sphere (but for those grazing its rim)."""
    camera = PinholeCamera(96, 64, 80.0, 80.0, 47.0, 33.5)  # principal point off centre
    vertices, faces = uv_sphere(1.0, 128, 256)
    depth = depth_buffer(vertices, faces, np.eye(3), np.array([0.0, 0.0, 4.0]), camera)
    x, y = pixel_rays(camera)
    # |s (x, y, 1) - (0, 0, 4)| = 1: (x² + y² + 1) s² - 8 s + 15 = 0.
    a = x ** 2 + y ** 2 + 1
    disc = 64 - 60 * a
    hit = disc > 0
    analytic = np.where(hit, (8 - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    firm = disc > 0.5  # away from the rim, where tessellation decides coverage
    assert np.isfinite(depth[firm]).all() and np.isinf(depth[~hit]).all()
    np.testing.assert_allclose(depth[firm], analytic[firm], atol=5e-4)


def test_depth_buffer_clips_a_ground_plane_reaching_behind_the_camera():
    """A two-triangle plane y = 1 (below the camera, y down) from 10 units behind to 50 ahead:
    its depth at each pixel centre below the horizon is 1 / y_ray, exactly."""
    camera = PinholeCamera(64, 48, 40.0, 40.0, 32.0, 24.0)
    plane = np.array([[-50, 1, -10], [50, 1, -10], [50, 1, 50], [-50, 1, 50]], float)
    depth = depth_buffer(plane, np.array([[0, 1, 2], [0, 2, 3]]), np.eye(3), np.zeros(3), camera)
    x, y = pixel_rays(camera)
    analytic = np.where(y > 0, 1 / np.where(y > 0, y, 1), np.inf)
    within = (analytic < 50) & (np.abs(x * analytic) < 50)  # the plane's extent
    np.testing.assert_allclose(depth[within], analytic[within], rtol=1e-9)
    assert np.isinf(depth[y < 0]).all()


def test_points_are_seen_unless_behind_a_surface_or_at_grazing_angles():
    camera = PinholeCamera(64, 64, 64.0, 64.0, 32.0, 32.0)
    wall = np.array([[-0.5, -0.5, 2], [0.5, -0.5, 2], [0.5, 0.5, 2], [-0.5, 0.5, 2]], float)
    floor = np.array([[-3, 1, 1], [3, 1, 1], [3, 1, 9], [-3, 1, 9]], float)  # y = 1, seen from above
    vertices = np.concatenate([wall, floor])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    depth = depth_buffer(vertices, faces, np.eye(3), np.zeros(3), camera)
    points = np.array([[0.1, 0.2, 2.0],    # on the wall
                       [0.2, 1.0, 3.0],    # on the floor, in the open
                       [0.0, 1.0, 5.0],    # on the floor, hidden by the wall (its ray passes y = 0.4 at z = 2)
                       [2.5, 1.0, 1.5]])   # on the floor, outside the image
    up = np.array([0.0, -1.0, 0.0])
    normals = np.array([[0, 0, -1.0], up, up, up])
    seen, pixels = points_seen(points, normals, np.eye(3), np.zeros(3), camera, depth)
    assert seen.tolist() == [True, True, False, False]
    np.testing.assert_allclose(pixels[0], [32 + 64 * 0.05, 32 + 64 * 0.1])
    # The floor seen edge-on (camera at its height): every point grazes, none is seen.
    flat = depth_buffer(floor - [0, 1, 0], faces[2:] - 4, np.eye(3), np.zeros(3), camera)
    seen, _ = points_seen(np.array([[0.0, 0.0, 3.0]]), up[None], np.eye(3), np.zeros(3), camera, flat)
    assert not seen[0] and GRAZING_COS > 0


def filtered_png(image: np.ndarray, filters: list[int]) -> bytes:
    """An RGBA PNG whose row y uses filter ``filters[y]`` (PNG spec, section 9.2), so the reader
    meets each of the five filters."""
    height, width, channels = image.shape
    data = image.reshape(height, width * channels).astype(np.int32)
    rows = []
    for y, kind in enumerate(filters):
        row, prior = data[y], data[y - 1] if y else np.zeros_like(data[0])
        left = np.concatenate([np.zeros(channels, np.int32), row[:-channels]])
        upper_left = np.concatenate([np.zeros(channels, np.int32), prior[:-channels]])
        if kind == 0:
            predicted = np.zeros_like(row)
        elif kind == 1:
            predicted = left
        elif kind == 2:
            predicted = prior
        elif kind == 3:
            predicted = (left + prior) // 2
        else:
            p = left + prior - upper_left
            pa, pb, pc = np.abs(p - left), np.abs(p - prior), np.abs(p - upper_left)
            predicted = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, prior, upper_left))
        rows.append(bytes([kind]) + ((row - predicted) % 256).astype(np.uint8).tobytes())

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"".join(rows)))
            + chunk(b"IEND", b""))


def test_png_reader_undoes_every_row_filter_as_pillow_does(tmp_path):
    image = np.random.default_rng(3).integers(0, 256, size=(10, 7, 4), dtype=np.uint8)
    path = tmp_path / "filters.png"
    path.write_bytes(filtered_png(image, [0, 1, 2, 3, 4, 4, 3, 2, 1, 0]))
    with Image.open(path) as reference:
        np.testing.assert_array_equal(np.asarray(reference), image)  # the test's encoder is right
    np.testing.assert_array_equal(read_png(str(path)), image)
    for shape in ((5, 6), (5, 6, 3), (5, 6, 4)):  # and what png_bytes writes, Pillow reads
        written = np.random.default_rng(4).integers(0, 256, size=shape, dtype=np.uint8)
        with Image.open(io.BytesIO(png_bytes(written))) as reference:
            np.testing.assert_array_equal(np.asarray(reference), written)


# --- a real dataset ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("colmap") / "A"
    result = run_module(str(SCENE), "--out", str(out), "--width", str(WIDTH), "--height", str(HEIGHT),
                        "--train-views", str(TRAIN_VIEWS), "--val-views", "1", "--test-views", "3",
                        "--samples", "16", "--format", "colmap", "--format", "ngp", "--no-progress")
    assert result.returncode == 0, result.stderr
    assert "COLMAP model: 16 images" in result.stderr
    return out


def read_model(dataset: Path, kind: str, tmp_path: Path) -> pycolmap.Reconstruction:
    """The model from its .txt or its .bin files alone (pycolmap prefers .bin when both are there)."""
    folder = tmp_path / kind
    folder.mkdir()
    for path in (dataset / "colmap" / "sparse" / "0").glob(f"*.{kind}"):
        shutil.copy(path, folder)
    assert len(list(folder.iterdir())) == 3
    return pycolmap.Reconstruction(str(folder))


def model_figures(dataset: Path, model: pycolmap.Reconstruction) -> dict:
    """What the checks below measure, for any dataset written with --format colmap (also printed
    by ``python tests/test_colmap_format.py DATASET``): every 3D point projected through
    pycolmap's camera model and pose into every image that lists it, against the render's alpha
    and the 2D point written; camera centres and intrinsics against the nerf_synthetic JSON;
    tracks against 2D points; colours against pycolmap's own extraction from images/."""
    train = load_split(dataset, "train")
    frames = {Path(frame["file_path"]).name + ".png": frame for frame in train["frames"]}
    intrinsics = [train["fl_x"], train["fl_y"], train["cx"], train["cy"]]
    figures = {"images": model.num_images(), "cameras": model.num_cameras(), "points": model.num_points3D(),
               "observations": 0, "inside_alpha": 0, "fewest_observations_in_an_image": None,
               "worst_projection_px": 0.0, "worst_centre": 0.0, "worst_intrinsic_rel": 0.0,
               "pinhole": all(camera.model_name == "PINHOLE" for camera in model.cameras.values()),
               "sizes": sorted({(camera.width, camera.height) for camera in model.cameras.values()})}
    for image in model.images.values():
        frame = frames[image.name]
        camera = model.cameras[image.camera_id]
        centre = np.abs(image.projection_center() - np.asarray(frame["transform_matrix"])[:3, 3]).max()
        figures["worst_centre"] = max(figures["worst_centre"], float(centre))
        figures["worst_intrinsic_rel"] = max(figures["worst_intrinsic_rel"], float(
            np.max(np.abs(np.asarray(camera.params) - intrinsics) / np.abs(intrinsics))))
        alpha = np.asarray(Image.open(dataset / (frame["file_path"] + ".png")))[..., 3]
        observed = [point for point in image.points2D if point.has_point3D()]
        xyz = np.array([model.points3D[point.point3D_id].xyz for point in observed])
        projected = np.array([camera.img_from_cam(image.cam_from_world() * p) for p in xyz])
        written = np.array([point.xy for point in observed])
        figures["worst_projection_px"] = max(figures["worst_projection_px"], float(np.abs(projected - written).max()))
        i, j = np.floor(projected).astype(int).T
        figures["inside_alpha"] += int((alpha[j, i] > 127).sum())
        figures["observations"] += len(observed)
        fewest = figures["fewest_observations_in_an_image"]
        figures["fewest_observations_in_an_image"] = len(observed) if fewest is None else min(fewest, len(observed))
    figures["inside_alpha_fraction"] = figures["inside_alpha"] / figures["observations"]
    figures["track_mismatches"] = sum(
        model.images[element.image_id].points2D[element.point2D_idx].point3D_id != point_id
        for point_id, point in model.points3D.items() for element in point.track.elements)
    ids = sorted(model.points3D)
    written = np.array([model.points3D[i].color for i in ids], float)
    model.extract_colors_for_all_images(str(dataset / "colmap" / "images"))
    difference = np.abs(written - np.array([model.points3D[i].color for i in ids], float))
    figures["colour_difference_median"] = float(np.median(difference))
    figures["colour_difference_p99"] = float(np.percentile(difference, 99))
    figures["colour_difference_max"] = float(difference.max())
    return figures


@pytest.mark.parametrize("kind", ["txt", "bin"])
def test_pycolmap_reads_the_model_and_its_points_project_onto_the_object(dataset, kind, tmp_path):
    """Every 3D point projected through pycolmap's camera model and pose into every image that
    lists it lands inside the rendered alpha mask (>= 99 %) and on the 2D point written (0.5 px
    is the issue's bound; they agree to 1e-3 px); camera centres equal the nerf_synthetic JSON's
    to 1e-6; the one PINHOLE camera is the JSON's exact intrinsics; every track element names a
    2D point that names its 3D point back; pycolmap's own colour extraction (bilinear, from
    images/) gives the written colours to a level (rounding)."""
    figures = model_figures(dataset, read_model(dataset, kind, tmp_path))
    assert (figures["images"], figures["cameras"], figures["pinhole"]) == (TRAIN_VIEWS, 1, True)
    assert figures["sizes"] == [(WIDTH, HEIGHT)] and figures["worst_intrinsic_rel"] <= 1e-15
    assert figures["points"] > 5000 and figures["fewest_observations_in_an_image"] > 1000
    assert figures["worst_projection_px"] < 1e-3
    assert figures["inside_alpha_fraction"] >= 0.99, figures
    assert figures["worst_centre"] <= 1e-6
    assert figures["track_mismatches"] == 0
    assert figures["colour_difference_max"] <= 1, figures


def test_images_and_masks_are_the_renders(dataset, tmp_path):
    """images/ holds each training render composited on white (as 3DGS composites nerf_synthetic
    views), masks/ its alpha."""
    for frame in load_split(dataset, "train")["frames"]:
        name = Path(frame["file_path"]).name + ".png"
        rgba = np.asarray(Image.open(dataset / (frame["file_path"] + ".png"))).astype(float) / 255
        on_white = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:])
        with Image.open(dataset / "colmap" / "images" / name) as image:
            assert image.mode == "RGB"
            assert np.abs(np.asarray(image) - on_white * 255).max() <= 0.5 + 1e-9
        with Image.open(dataset / "colmap" / "masks" / name) as mask:
            assert mask.mode == "L"
            np.testing.assert_array_equal(np.asarray(mask), (rgba[..., 3] * 255).round())


def test_points3d_ply_is_the_models_points_for_3dgs_and_nerfstudio(dataset, tmp_path):
    """points3d.ply (beside transforms_train.json, where 3DGS's nerf_synthetic reader looks)
    holds the model's points as x y z nx ny nz red green blue; transforms.json names it as
    nerfstudio's ply_file_path."""
    data = (dataset / "points3d.ply").read_bytes()
    header, body = data.split(b"end_header\n", 1)
    lines = header.decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    assert [line.split()[-1] for line in lines if line.startswith("property")] == [
        "x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    rows = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("normal", "<f4", 3), ("rgb", "u1", 3)])
    model = read_model(dataset, "bin", tmp_path)
    ids = sorted(model.points3D)
    assert len(rows) == len(ids)
    np.testing.assert_allclose(rows["xyz"], [model.points3D[i].xyz for i in ids], atol=1e-6)
    np.testing.assert_array_equal(rows["rgb"], [model.points3D[i].color for i in ids])
    np.testing.assert_allclose(np.linalg.norm(rows["normal"], axis=1), 1, atol=1e-6)
    assert json.loads((dataset / "transforms.json").read_text())["ply_file_path"] == "points3d.ply"


def depth_figures(dataset: Path) -> list[dict]:
    """Per test view (which have Cycles' depth pass): how the depth buffer of scene_geometry.ply
    and the points the export would call seen compare with what Cycles rendered."""
    test = load_split(dataset, "test")
    vertices, faces = read_ply(str(dataset / "scene_geometry.ply"))
    points, normals = sample_surface(vertices, faces, 20_000, seed=0)
    camera = PinholeCamera(test["w"], test["h"], test["fl_x"], test["fl_y"], test["cx"], test["cy"])
    x, y = pixel_rays(camera)
    ray_length = np.sqrt(x ** 2 + y ** 2 + 1)
    figures = []
    for frame in test["frames"]:
        rotation, translation = world_to_camera(frame["transform_matrix"])
        cycles = read_exr(dataset / frame["depth_file_path"])["Z"]  # distance along the ray; 0 = nothing
        depth = depth_buffer(vertices, faces, rotation, translation, camera)
        covered = cycles > 0
        both = covered & np.isfinite(depth)
        agree = np.abs(depth[both] * ray_length[both] - cycles[both]) <= 1e-3 * cycles[both]
        seen, _ = points_seen(points, normals, rotation, translation, camera, depth)
        pixels, z = project(points, rotation, translation, camera)
        in_image = (z > 0) & (pixels >= 0).all(axis=1) & (pixels[:, 0] < camera.width) & (pixels[:, 1] < camera.height)
        i, j = np.floor(pixels[in_image]).astype(int).T
        # Where the ray through the point's pixel centre meets the point's tangent plane (Cycles'
        # depth is taken there, not at the point).
        in_camera = points[in_image] @ rotation.T + translation
        normal = normals[in_image] @ rotation.T
        ray = np.stack([x[j, i], y[j, i], np.ones(len(i))], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            distance = (np.sum(normal * in_camera, 1) / np.sum(normal * ray, 1)) * ray_length[j, i]
        at_cycles_depth = np.abs(cycles[j, i] - distance) <= 0.01 * distance
        behind = cycles[j, i] < 0.99 * np.linalg.norm(in_camera, axis=1)
        figures.append({"view": frame["file_path"], "covered_pixels": int(covered.sum()),
                        "coverage_mismatch": float((covered != np.isfinite(depth)).mean()),
                        "depth_within_0.1%": float(agree.mean()), "seen": int(seen[in_image].sum()),
                        "seen_at_cycles_depth": float(at_cycles_depth[seen[in_image]].mean()),
                        "unseen_in_image": int((~seen[in_image]).sum()),
                        "unseen_behind_cycles_surface": float(behind[~seen[in_image]].mean())})
    return figures


def test_what_the_export_calls_seen_is_what_cycles_rendered(dataset):
    """On the test views, which have Cycles' depth pass: the depth buffer of scene_geometry.ply
    equals Cycles' depth to 0.1 % on >= 99.9 % of covered pixels (and covers the same pixels);
    >= 99 % of the points called seen lie at Cycles' depth (1 %); and of those in the image but
    not called seen, >= 85 % are behind what Cycles saw (the rest graze or straddle a pixel
    centre's silhouette, and are left out)."""
    for view in depth_figures(dataset):
        assert view["coverage_mismatch"] <= 1e-3, view
        assert view["depth_within_0.1%"] >= 0.999, view
        assert view["seen_at_cycles_depth"] >= 0.99, view
        assert view["unseen_behind_cycles_surface"] >= 0.85, view


def test_a_missing_render_is_named_and_the_earlier_export_is_kept(dataset, tmp_path):
    copy = tmp_path / "A"
    shutil.copytree(dataset, copy)
    before = sorted(str(path.relative_to(copy)) for path in (copy / "colmap").rglob("*"))
    (copy / "train" / "r_3.png").unlink()
    documents = {split: load_split(copy, split) for split in ("train", "val", "test")}
    profile = json.loads((copy / "scene_profile.json").read_text())
    with pytest.raises(DatasetGenError, match=r"cannot read the render .*train/r_3\.png"):
        write_colmap(str(copy), documents, profile, progress=False)
    assert sorted(str(path.relative_to(copy)) for path in (copy / "colmap").rglob("*")) == before
    assert not [path for path in copy.iterdir() if path.name.startswith(".")], "a partial export was left"


def test_a_run_without_the_layouts_removes_the_earlier_runs(dataset, tmp_path):
    """--overwrite with other formats: an earlier COLMAP model (or transforms.json) would describe
    renders that are no longer there, so only the layouts asked for are left."""
    copy = tmp_path / "A"
    shutil.copytree(dataset, copy)
    result = run_module(str(SCENE), "--out", str(copy), "--width", "40", "--height", "30", "--train-views", "4",
                        "--val-views", "1", "--test-views", "1", "--samples", "4", "--format", "ngp",
                        "--overwrite", "--no-progress")
    assert result.returncode == 0, result.stderr
    assert not (copy / "colmap").exists() and not (copy / "points3d.ply").exists()
    ngp = json.loads((copy / "transforms.json").read_text())
    assert "ply_file_path" not in ngp and len(ngp["frames"]) == 6


def test_resume_adds_or_removes_a_layout_without_rendering_again(dataset, tmp_path):
    """--resume with other --format flags: nothing is rendered; the layouts asked for are written
    (the same COLMAP model, byte for byte) and the others removed."""
    copy = tmp_path / "A"
    shutil.copytree(dataset, copy)
    arguments = [str(SCENE), "--out", str(copy), "--width", str(WIDTH), "--height", str(HEIGHT),
                 "--train-views", str(TRAIN_VIEWS), "--val-views", "1", "--test-views", "3", "--samples", "16",
                 "--resume", "--no-progress"]
    dropped = run_module(*arguments)
    assert dropped.returncode == 0, dropped.stderr
    assert "no view to render" in dropped.stderr
    assert not (copy / "colmap").exists() and not (copy / "points3d.ply").exists()
    assert not (copy / "transforms.json").exists()
    added = run_module(*arguments, "--format", "colmap")
    assert added.returncode == 0, added.stderr
    assert "no view to render" in added.stderr
    for path in sorted((dataset / "colmap").rglob("*")) + [dataset / "points3d.ply"]:
        if path.is_file():
            assert (copy / path.relative_to(dataset)).read_bytes() == path.read_bytes(), path


@pytest.mark.blender_binary
def test_a_blender_without_numpy_refuses_colmap_before_rendering(tmp_path):
    """Debian's blender has no numpy: --format colmap stops at once, saying why, and renders nothing."""
    blender = require_blender()
    out = tmp_path / "dataset"
    result = subprocess.run([blender, "-b", "--python", str(REPO / "datasets_gen" / "generate.py"), "--", *DEMO_ARGS,
                             "--out", str(out), "--format", "colmap"], capture_output=True, text=True, timeout=300)
    if "this Blender's Python has no numpy" not in result.stderr and result.returncode == 0:
        pytest.skip("this blender has numpy: it writes the COLMAP model like the bpy module")
    assert result.returncode == 2, result.stderr[-2000:]
    assert "--format colmap cannot sample points on the scene's surface: this Blender's Python has no numpy" \
        in result.stderr
    assert not list(out.rglob("*.png"))


if __name__ == "__main__":  # python tests/test_colmap_format.py DATASET: the figures, for any dataset
    import sys
    import tempfile

    for kind in ("txt", "bin"):
        with tempfile.TemporaryDirectory() as folder:
            print(kind, json.dumps(model_figures(Path(sys.argv[1]), read_model(Path(sys.argv[1]), kind, Path(folder)))))
    for view in depth_figures(Path(sys.argv[1])):
        print("against Cycles' depth", json.dumps(view))
