"""The dataset generator end to end, with real Blender (bpy module) and real Cycles renders.

Everything renders tiny (32x32 datasets, <= 64x64 marker images) so the file runs in seconds.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import OpenEXR
import pytest
from PIL import Image

from datasets_gen.core import trajectories as tr
from datasets_gen.core.intrinsics import camera_intrinsics
from nerf_backend.core.ply import read_face_materials, read_ply
from nerf_backend.data.occupancy_prior import load_occupancy_prior
from nerf_contract.dataset_layout import APPEARANCE_REGIONS

REPO = Path(__file__).resolve().parents[1]
SCRIPTS = Path(__file__).resolve().parent / "blender_scripts"
SPLIT_VIEWS = {"train": 6, "val": 2, "test": 4}
SIZE = 32
SEED = 0
DEMO_ARGS = [
    "--demo",
    "--train-views", str(SPLIT_VIEWS["train"]),
    "--val-views", str(SPLIT_VIEWS["val"]),
    "--test-views", str(SPLIT_VIEWS["test"]),
    "--resolution", str(SIZE),
    "--samples", "8",
    "--seed", str(SEED),
]
RADIUS = math.sqrt(16.25)
MIN_ELEVATION_DEG = math.degrees(math.atan2(0.5, 4.0))  # 7.125


def subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def run_module(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    """`python -m datasets_gen ARGS` with this interpreter (the venv's, which has bpy)."""
    return subprocess.run(
        [sys.executable, "-m", "datasets_gen", *args],
        cwd=cwd, env=subprocess_env(), capture_output=True, text=True, timeout=300,
    )


def load_split(dataset: Path, split: str) -> dict:
    return json.loads((dataset / f"transforms_{split}.json").read_text())


def read_exr(path: Path) -> dict[str, np.ndarray]:
    with OpenEXR.File(str(path)) as image:
        return {name: np.array(channel.pixels) for name, channel in image.channels().items()}


def expected_poses(split: str, count: int) -> list[tr.RigPose]:
    if split == "test":
        return tr.test_spiral_poses(count)
    return tr.hemisphere_poses(count, tr.split_rng(SEED, split))


@pytest.fixture(scope="module")
def demo_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo") / "dataset"
    result = run_module(*DEMO_ARGS, "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    return out


# --- (a) the module entry point writes a nerf_synthetic dataset -------------------------------


def test_layout_follows_nerf_synthetic(demo_dataset: Path) -> None:
    for split, count in SPLIT_VIEWS.items():
        document = load_split(demo_dataset, split)
        for key in ("camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h", "frames", "generator"):
            assert key in document, f"{split}: missing {key}"
        assert len(document["frames"]) == count
        # Depth and normal EXRs by default for the test split only (--depth-normals test).
        extra = {"depth_file_path", "normal_file_path"} if split == "test" else set()
        assert ("depth_normals" in document) == (split == "test")
        for index, frame in enumerate(document["frames"]):
            assert set(frame) == {"file_path", "rotation", "transform_matrix"} | extra
            assert frame["file_path"] == f"./{split}/r_{index}"  # no extension, as the loaders expect
            assert (demo_dataset / (frame["file_path"] + ".png")).is_file()
            for key in extra:
                assert frame[key] == f"./{split}/r_{index}_{key.split('_')[0]}.exr"
                assert (demo_dataset / frame[key]).is_file()
            matrix = np.asarray(frame["transform_matrix"])
            assert matrix.shape == (4, 4)
            np.testing.assert_allclose(matrix[3], [0, 0, 0, 1])
            assert frame["rotation"] == pytest.approx(2 * math.pi / count)
    leftovers = [p.name for p in demo_dataset.rglob("*") if p.name.startswith(".") or p.suffix == ".tmp"]
    assert leftovers == [], "temporary files left behind"


def test_images_are_rgba8_with_transparent_background(demo_dataset: Path) -> None:
    for split, count in SPLIT_VIEWS.items():
        for index in range(count):
            with Image.open(demo_dataset / split / f"r_{index}.png") as image:
                assert image.mode == "RGBA"  # 4 channels, 8 bits each
                assert image.size == (SIZE, SIZE)
                alpha = np.asarray(image)[..., 3]
            assert (alpha == 0).mean() > 0.2, "background must be transparent"
            assert (alpha == 255).sum() > 20, "the object must be opaque"


def test_intrinsics_are_the_protocol_camera(demo_dataset: Path) -> None:
    document = load_split(demo_dataset, "train")
    assert document["camera_angle_x"] == pytest.approx(0.6911112, abs=1e-7)
    assert document["fl_x"] == pytest.approx(SIZE / 36 * 50) and document["fl_y"] == document["fl_x"]
    assert (document["w"], document["h"], document["cx"], document["cy"]) == (SIZE, SIZE, SIZE / 2, SIZE / 2)
    # What the reference loaders derive from camera_angle_x must match fl_x.
    assert 0.5 * SIZE / math.tan(0.5 * document["camera_angle_x"]) == pytest.approx(document["fl_x"])


def test_poses_follow_the_protocol_and_the_pure_maths(demo_dataset: Path) -> None:
    for split, count in SPLIT_VIEWS.items():
        frames = load_split(demo_dataset, split)["frames"]
        for frame, pose in zip(frames, expected_poses(split, count)):
            matrix = np.asarray(frame["transform_matrix"])
            position = matrix[:3, 3]
            assert np.linalg.norm(position) == pytest.approx(RADIUS, abs=1e-5)
            elevation = math.degrees(math.asin(position[2] / np.linalg.norm(position)))
            assert MIN_ELEVATION_DEG - 1e-3 <= elevation <= 90.0
            np.testing.assert_allclose(matrix, np.asarray(pose.matrix), atol=1e-5)
    first_test = np.asarray(load_split(demo_dataset, "test")["frames"][0]["transform_matrix"])
    assert math.degrees(math.asin(first_test[2, 3] / RADIUS)) == pytest.approx(47.2, abs=0.05)


def test_generator_records_the_settings(demo_dataset: Path) -> None:
    record = load_split(demo_dataset, "val")["generator"]
    expected = {
        "engine": "CYCLES",
        "device": "CPU",
        "samples": 8,
        "seed": SEED,
        "denoising": False,
        "resolution": [SIZE, SIZE],
        "resolution_percentage": 100,
        "view_transform": "Standard",
        "look": "None",
        "exposure": 0.0,
        "gamma": 1.0,
        "film_transparent": True,
        "dither": 0.0,
        "train_val_trajectory": "hemisphere",
        "views": SPLIT_VIEWS,
        "scene_source": "demo",
    }
    for key, value in expected.items():
        assert record[key] == value, key
    assert record["blender_version"].startswith(("5.", "4."))
    assert record["image"] == {"file_format": "PNG", "color_mode": "RGBA", "color_depth": "8"}
    assert record["camera"]["lens_mm"] == 50.0 and record["camera"]["sensor_fit"] == "AUTO"
    assert record["depth_normals"] == "test" and record["allow_missing"] is False
    assert record["scene_checks"]["errors"] == [] and record["scene_checks"]["notes"] == []
    settings = record["settings"]
    assert settings["scene"] == {"source": "demo", "demo_variant": "standard"}
    assert settings["frame"] == "blender" and settings["samples"] == 8 and settings["views"] == SPLIT_VIEWS
    assert load_split(demo_dataset, "train")["generator"] == record


def test_the_demo_is_recorded_in_the_identity_frame(demo_dataset: Path) -> None:
    """The demo is modelled in the protocol frame: world_to_nerf is the identity, in every JSON."""
    profile = json.loads((demo_dataset / "scene_profile.json").read_text())
    for document in [profile] + [load_split(demo_dataset, split) for split in SPLIT_VIEWS]:
        frame = document["world_to_nerf"]
        assert frame["scale"] == 1.0 and frame["translation"] == [0.0, 0.0, 0.0]
        np.testing.assert_array_equal(frame["matrix"], np.eye(4))
        assert "demo" in frame["rule"] and "identity" in frame["rule"]
    # The gold sphere is metallic: the standard demo is view-dependent; its profile says which and why.
    assert profile["view_dependent"] is True and profile["transparency"] is False
    gold = next(material for material in profile["materials"] if material["name"] == "gold")
    assert gold["view_dependent"] and any("metallic 1" in reason for reason in gold["reasons"])
    assert gold["objects"] == ["gold sphere"]
    assert profile["image_size"] == [SIZE, SIZE]
    assert [light["type"] for light in profile["lights"]] == ["SUN"]
    assert profile["world"]["kind"] == "uniform colour"


def test_public_nerf_synthetic_loader_steps(demo_dataset: Path) -> None:
    """What the reference loaders do, step by step: JSON, file_path + ".png", RGBA / 255 on white,
    focal from camera_angle_x, 4x4 poses; nothing else in the dataset is needed."""
    for split in SPLIT_VIEWS:
        meta = json.loads((demo_dataset / f"transforms_{split}.json").read_text())
        images = np.stack([imageio.imread(demo_dataset / (frame["file_path"] + ".png")) for frame in meta["frames"]])
        poses = np.stack([np.array(frame["transform_matrix"], dtype=np.float32) for frame in meta["frames"]])
        images = images.astype(np.float32) / 255.0
        assert images.shape == (SPLIT_VIEWS[split], SIZE, SIZE, 4) and poses.shape == (SPLIT_VIEWS[split], 4, 4)
        rgb = images[..., :3] * images[..., 3:] + (1.0 - images[..., 3:])  # white background
        assert rgb.min() >= 0.0 and rgb.max() <= 1.0 and (rgb == 1.0).all(axis=-1).mean() > 0.2
        height, width = images.shape[1:3]
        focal = 0.5 * width / np.tan(0.5 * float(meta["camera_angle_x"]))
        assert focal == pytest.approx(meta["fl_x"]) and (height, width) == (meta["h"], meta["w"])


def test_diffuse_demo_variant_is_view_independent() -> None:
    """--demo-variant diffuse: same scene, every material a Diffuse BSDF; --check renders nothing."""
    result = run_module("--demo", "--demo-variant", "diffuse", "--check")
    assert result.returncode == 0, result.stderr
    profile = json.loads(result.stdout[result.stdout.index("\n{\n") + 1:] if "\n{\n" in result.stdout
                         else result.stdout)
    assert profile["view_dependent"] is False and profile["transparency"] is False
    assert {material["name"] for material in profile["materials"]} == {
        "pedestal", "gold", "checker", "brick", "rod", "ring"}
    assert not any(material["view_dependent"] for material in profile["materials"])
    assert profile["world_to_nerf"]["scale"] == 1.0


def test_a_gpu_that_is_not_there_is_a_clear_error(tmp_path: Path) -> None:
    out = tmp_path / "never"
    result = run_module(*DEMO_ARGS, "--device", "OPTIX", "--out", str(out))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert "--device OPTIX" in line and "--device CPU" in line
    assert not out.exists()


def test_scene_profile_bounds_hold_every_rendered_pixel(demo_dataset: Path) -> None:
    """Bounds are small, non-degenerate, and their projection covers each view's opaque pixels."""
    profile = json.loads((demo_dataset / "scene_profile.json").read_text())
    assert profile["version"] == 2 and profile["source"] == "demo"
    low, high = np.asarray(profile["bounds"]["min"]), np.asarray(profile["bounds"]["max"])
    assert np.all(high - low > 0.5), "degenerate bounds"
    # Inside the cube [-1.5, 1.5]^3 that nerf_synthetic scenes are conventionally assumed to fill.
    assert np.all(low > -1.5) and np.all(high < 1.5)
    corners = np.array([[x, y, z, 1.0] for x in (low[0], high[0]) for y in (low[1], high[1]) for z in (low[2], high[2])])
    for split in SPLIT_VIEWS:
        document = load_split(demo_dataset, split)
        for frame in document["frames"]:
            world_to_camera = np.linalg.inv(np.asarray(frame["transform_matrix"]))
            camera_points = (world_to_camera @ corners.T).T[:, :3]
            u = document["cx"] + document["fl_x"] * camera_points[:, 0] / -camera_points[:, 2]
            v = document["cy"] - document["fl_y"] * camera_points[:, 1] / -camera_points[:, 2]
            with Image.open(demo_dataset / (frame["file_path"] + ".png")) as image:
                alpha = np.asarray(image)[..., 3]
            rows, columns = np.nonzero(alpha > 0)
            margin = 1.5  # Cycles' pixel filter spreads edges by up to its 1.5 px width
            assert columns.min() + 0.5 >= u.min() - margin and columns.max() + 0.5 <= u.max() + margin
            assert rows.min() + 0.5 >= v.min() - margin and rows.max() + 0.5 <= v.max() + margin


def test_scene_geometry_is_the_renderable_triangles_in_the_profile_bounds(demo_dataset: Path) -> None:
    """scene_geometry.ply (the truth eval --geometry measures against): as many triangles as the
    profile records, every vertex inside the profile's bounds (float32 in the file)."""
    profile = json.loads((demo_dataset / "scene_profile.json").read_text())
    record = profile["geometry"]
    assert record["file"] == "scene_geometry.ply" and record["frame"].startswith("NeRF frame")
    assert record["left_out"] == []  # the demo has nothing to_mesh cannot measure
    vertices, faces = read_ply(demo_dataset / record["file"])
    assert len(faces) == record["triangles"] > 100 and len(vertices) == record["vertices"]
    low, high = np.asarray(profile["bounds"]["min"]), np.asarray(profile["bounds"]["max"])
    assert (vertices >= low - 1e-5).all() and (vertices <= high + 1e-5).all()
    np.testing.assert_allclose(vertices.min(axis=0), low, atol=1e-5)  # the bounds are the triangles'
    np.testing.assert_allclose(vertices.max(axis=0), high, atol=1e-5)
    # Each triangle's material, an index into the profile's materials: every material an object
    # carries is some triangles', and a triangle's material is its region's in the prior's cells.
    materials = read_face_materials(demo_dataset / record["file"])
    names = [material["name"] for material in profile["materials"]]
    assert materials is not None and len(materials) == len(faces) and materials.max() < len(names)
    assert {names[i] for i in set(materials.tolist())} == {m["name"] for m in profile["materials"] if m["objects"]}
    prior = load_occupancy_prior(demo_dataset, "surface")
    centres = vertices[faces].mean(axis=1)
    cells = np.clip(((centres - np.asarray(prior.box_min)) / prior.cell_size).astype(int), 0,
                    np.asarray(prior.regions.shape) - 1)
    in_cells = prior.regions.numpy()[cells[:, 0], cells[:, 1], cells[:, 2]]
    of_material = np.array([APPEARANCE_REGIONS.index(m["region"]) for m in profile["materials"]])[materials]
    assert (in_cells == of_material).mean() > 0.9  # cells two regions share hold the later one


# --- the pure rig maths reproduces the protocol's Blender rig (Empty + child camera + Track-To) --


def test_pure_rig_maths_matches_blenders_track_to_rig(tmp_path: Path) -> None:
    poses = tr.hemisphere_poses(24, tr.split_rng(1, "train")) + tr.test_spiral_poses(200)[::20]
    poses += tr.hemisphere_poses(8, tr.split_rng(1, "val"), full_sphere=True)
    angles_path, out_path = tmp_path / "angles.json", tmp_path / "matrices.json"
    angles_path.write_text(json.dumps([[pose.tilt_x, pose.azimuth_z] for pose in poses]))
    result = subprocess.run(
        [sys.executable, str(SCRIPTS / "protocol_rig.py"), str(angles_path), str(out_path)],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    for pose, blender_matrix in zip(poses, json.loads(out_path.read_text())):
        np.testing.assert_allclose(np.asarray(blender_matrix), np.asarray(pose.matrix), atol=1e-5)


# --- (b) intrinsics proven by projecting emissive markers into real renders -------------------

MARKERS = [[0.0, 0.0, 0.0], [0.3, 0.35, 0.3], [-0.3, -0.3, -0.25]]
MARKER_CAMERA = tr.look_at((2.6, -2.2, 1.3))
MARKER_CASES = {
    "square": dict(resolution=[48, 48]),
    "landscape_shift": dict(resolution=[64, 48], shift=[0.1, 0.05]),
    "portrait_auto_shift": dict(resolution=[48, 64], shift=[-0.08, 0.06]),
    "vertical_fit_shift": dict(resolution=[64, 48], sensor_fit="VERTICAL", shift=[0.05, -0.07], lens=25.0),
    "horizontal_fit_portrait": dict(resolution=[48, 64], sensor_fit="HORIZONTAL", shift=[0.05, 0.1]),
    "percentage_and_wide_pixels": dict(resolution=[128, 96], percentage=50, pixel_aspect=[2.0, 1.0], shift=[0.04, 0.03]),
    "tall_pixels_flip_auto_fit": dict(resolution=[48, 64], pixel_aspect=[1.0, 1.5], shift=[0.04, -0.03]),
}


@pytest.fixture(scope="module")
def marker_renders(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("markers")
    base = dict(lens=35.0, sensor_width=36.0, sensor_height=24.0, sensor_fit="AUTO", shift=[0.0, 0.0],
                percentage=100, pixel_aspect=[1.0, 1.0], samples=64,
                matrix_world=[list(row) for row in MARKER_CAMERA])
    cases = [dict(base, name=name, **overrides) for name, overrides in MARKER_CASES.items()]
    (out / "cases.json").write_text(json.dumps({"markers": MARKERS, "cases": cases}))
    result = subprocess.run(
        [sys.executable, str(SCRIPTS / "render_markers.py"), str(out / "cases.json"), str(out)],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    return out


@pytest.mark.parametrize("case", sorted(MARKER_CASES))
def test_intrinsics_match_a_real_render(marker_renders: Path, case: str) -> None:
    """Each marker's intensity-weighted centroid lands within 0.5 px of its projection."""
    camera = json.loads((marker_renders / f"{case}.json").read_text())
    pixels = np.load(marker_renders / f"{case}.npy")
    k = camera_intrinsics(
        lens_mm=camera["lens"], sensor_width_mm=camera["sensor_width"],
        sensor_height_mm=camera["sensor_height"], sensor_fit=camera["sensor_fit"],
        resolution_x=camera["resolution"][0], resolution_y=camera["resolution"][1],
        resolution_percentage=camera["percentage"],
        pixel_aspect_x=camera["pixel_aspect"][0], pixel_aspect_y=camera["pixel_aspect"][1],
        shift_x=camera["shift"][0], shift_y=camera["shift"][1],
    )
    assert pixels.shape[:2] == (k.h, k.w)
    world_to_camera = np.linalg.inv(np.asarray(camera["matrix_world"]))
    rows, columns = np.mgrid[0:k.h, 0:k.w] + 0.5  # pixel centres at i + 0.5
    for channel, marker in enumerate(MARKERS):
        u, v = k.project((world_to_camera @ np.array([*marker, 1.0]))[:3])
        assert 3 <= u <= k.w - 3 and 3 <= v <= k.h - 3, "test setup: marker must be well inside the image"
        weights = pixels[..., channel]
        assert weights.sum() > 0, f"marker {channel} not visible"
        centroid = ((weights * columns).sum() / weights.sum(), (weights * rows).sum() / weights.sum())
        assert centroid == (pytest.approx(u, abs=0.5), pytest.approx(v, abs=0.5)), (case, channel)


# --- (c) `blender -b --python datasets_gen/generate.py` with a Blender executable -------------


def require_blender() -> str:
    """Path of a `blender` executable; skip without one unless NERF_REQUIRE_BLENDER=1 (then fail)."""
    blender = shutil.which("blender")
    if blender is None:
        if os.environ.get("NERF_REQUIRE_BLENDER") == "1":
            pytest.fail("NERF_REQUIRE_BLENDER=1 but no `blender` executable is on PATH")
        pytest.skip("no `blender` executable on PATH (set NERF_REQUIRE_BLENDER=1 to make this a failure)")
    return blender


@pytest.fixture(scope="module")
def blender_executable() -> str:
    return require_blender()


@pytest.mark.blender_binary
def test_blender_binary_entry_point_matches_module(
    blender_executable: str, demo_dataset: Path, tmp_path: Path
) -> None:
    blender = blender_executable
    out = tmp_path / "dataset"
    # Run from an unrelated folder: generate.py must find the package from its own path.
    result = subprocess.run(
        [blender, "-b", "--python", str(REPO / "datasets_gen" / "generate.py"), "--", *DEMO_ARGS,
         "--out", str(out)],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    for split in SPLIT_VIEWS:
        reference, produced = load_split(demo_dataset, split), load_split(out, split)
        assert sorted(produced) == sorted(reference)
        for key in ("camera_angle_x", "fl_x", "fl_y", "cx", "cy", "w", "h"):
            assert produced[key] == pytest.approx(reference[key]), key
        for frame, reference_frame in zip(produced["frames"], reference["frames"], strict=True):
            assert frame["file_path"] == reference_frame["file_path"]
            assert (out / (frame["file_path"] + ".png")).is_file()
            np.testing.assert_allclose(frame["transform_matrix"], reference_frame["transform_matrix"], atol=1e-6)
        differing = {key for key in reference["generator"] if produced["generator"].get(key) != reference["generator"][key]}
        assert differing <= {"blender_version"}, differing
    with Image.open(out / "train" / "r_0.png") as image:
        assert image.mode == "RGBA" and image.size == (SIZE, SIZE)
    bounds = json.loads((out / "scene_profile.json").read_text())["bounds"]
    reference_bounds = json.loads((demo_dataset / "scene_profile.json").read_text())["bounds"]
    for key in ("min", "max"):
        np.testing.assert_allclose(bounds[key], reference_bounds[key], atol=1e-6)
    # Blender 3.4 writes its render passes as a single-part EXR (5.x: one part per pass): same depth.
    for index in range(SPLIT_VIEWS["test"]):
        produced_depth = read_exr(out / "test" / f"r_{index}_depth.exr")
        reference_depth = read_exr(demo_dataset / "test" / f"r_{index}_depth.exr")
        both = (produced_depth["Z"] > 0) & (reference_depth["Z"] > 0)
        assert both.sum() > 50
        np.testing.assert_allclose(produced_depth["Z"][both], reference_depth["Z"][both], atol=1e-3)


# --- (d) never clobber a folder, never leave half a dataset; bad input is one clear line -------


def test_refuses_a_non_empty_output_folder(tmp_path: Path) -> None:
    out = tmp_path / "existing"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "transforms_train.json").write_text("old")
    before = {p.name: (p.read_text(), p.stat().st_mtime_ns) for p in out.iterdir()}
    result = run_module(*DEMO_ARGS, "--out", str(out))
    assert result.returncode != 0
    message = result.stderr.strip().splitlines()
    assert len(message) == 1 and str(out) in message[0] and "--overwrite" in message[0]
    assert {p.name: (p.read_text(), p.stat().st_mtime_ns) for p in out.iterdir()} == before


def test_overwrite_replaces_the_dataset_and_keeps_other_files(tmp_path: Path) -> None:
    out = tmp_path / "existing"
    (out / "train").mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    (out / "train" / "r_7.png").write_bytes(b"stale")
    (out / "transforms_train.json").write_text("old")
    result = run_module("--demo", "--train-views", "1", "--val-views", "1", "--test-views", "1",
                        "--resolution", "16", "--samples", "2", "--overwrite", "--no-progress",
                        "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / "train" / "r_7.png").exists(), "stale frame of an earlier run must go"
    assert len(load_split(out, "train")["frames"]) == 1


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["missing.blend"], "missing.blend"),
        (["--demo", "--samples", "0"], "--samples"),
        (["--demo", "--resolution", "32", "--width", "32", "--height", "32"], "--resolution"),
        (["--demo", "--width", "32"], "--height"),
        (["--demo", "--device", "TPU"], "--device"),
        (["--demo", "--frobnicate"], "--frobnicate"),
        ([], "--demo"),
    ],
)
def test_bad_input_is_one_clear_line(tmp_path: Path, args: list[str], named: str) -> None:
    out = tmp_path / "never_created"
    result = run_module(*args, "--out", str(out), cwd=tmp_path)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and named in lines[0], result.stderr
    assert "Traceback" not in result.stderr
    assert not out.exists()
