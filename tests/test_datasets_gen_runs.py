"""Long-render machinery and exactness, with real bpy renders: resume after a killed run, shards
and merge, reproducibility, depth EXRs against analytic ray distances, and the dataset's
intrinsics and poses against emissive markers in real renders for every camera flag.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from test_datasets_gen import REPO, SCRIPTS, load_split, read_exr, run_module, subprocess_env

# 34 views of 48 x 48 at 16 samples (~0.03 s a view unloaded): the run is killed after 4 views,
# long before its end.
RUN_ARGS = ["--demo", "--resolution", "48", "--train-views", "24", "--val-views", "4", "--test-views", "6",
            "--samples", "16", "--seed", "3", "--no-progress"]


def dataset_files(dataset: Path) -> list[str]:
    return sorted(str(path.relative_to(dataset)) for path in dataset.rglob("*") if path.is_file())


def assert_same_dataset(produced: Path, reference: Path) -> None:
    """Same files; identical JSON; identical PNG pixels; EXRs equal to float round-off; the
    same occupancy prior (arrays equal; the zip's own timestamps may differ); every other file
    (scene geometry, points, the COLMAP model) byte for byte.

    Cycles' beauty pass is bit-identical for a fixed seed; its normal pass sums samples with
    atomic float adds whose order varies between runs, so normals may differ by ~1e-7.  PNG files
    are compared by pixels, not bytes: Cycles writes its render time into their metadata.
    """
    assert dataset_files(produced) == dataset_files(reference)
    for name in dataset_files(reference):
        if name.endswith(".json"):
            assert json.loads((produced / name).read_text()) == json.loads((reference / name).read_text()), name
        elif name.endswith(".png"):
            with Image.open(produced / name) as a, Image.open(reference / name) as b:
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=name)
        elif name.endswith(".exr"):
            a, b = read_exr(produced / name), read_exr(reference / name)
            assert a.keys() == b.keys()
            for channel in a:
                np.testing.assert_allclose(a[channel], b[channel], atol=1e-6, err_msg=f"{name} {channel}")
        elif name.endswith(".ply"):  # the scene's triangles: written the same way by every run and shard
            assert (produced / name).read_bytes() == (reference / name).read_bytes(), name
        elif name.endswith(".npz"):
            with np.load(produced / name) as a, np.load(reference / name) as b:
                assert a.files == b.files, name
                for key in a.files:
                    np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name} {key}")
        else:  # the COLMAP model's .txt and .bin files
            assert (produced / name).read_bytes() == (reference / name).read_bytes(), name


@pytest.fixture(scope="module")
def reference_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("reference") / "dataset"
    result = run_module(*RUN_ARGS, "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert (out / "occupancy_prior.npz").is_file()
    return out


def test_resume_after_a_killed_run_gives_the_uninterrupted_dataset(reference_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "dataset"
    process = subprocess.Popen([sys.executable, "-m", "datasets_gen", *RUN_ARGS, "--out", str(out)],
                               cwd=REPO, env=subprocess_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while len(list((out / "train").glob("r_*.png"))) < 4 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert process.returncode == -signal.SIGKILL, "the run finished before it could be killed"
    assert not (out / "transforms_train.json").exists() and (out / ".datasets_gen_progress.json").is_file()
    written = len(list((out / "train").glob("r_*.png")))
    assert 4 <= written < 24

    # Without --resume the folder is not touched; with other settings --resume refuses, naming them.
    refused = run_module(*RUN_ARGS, "--out", str(out))
    assert refused.returncode == 2 and "--resume" in refused.stderr
    different = [arg if arg != "16" else "8" for arg in RUN_ARGS]
    refused = run_module(*different, "--out", str(out), "--resume")
    assert refused.returncode == 2 and "samples 16 there vs 8 now" in refused.stderr

    resumed = run_module(*RUN_ARGS, "--out", str(out), "--resume")
    assert resumed.returncode == 0, resumed.stderr
    assert f"{written} views already complete" in resumed.stderr
    assert_same_dataset(out, reference_run)

    # Resuming a complete dataset renders nothing and changes nothing.
    again = run_module(*RUN_ARGS, "--out", str(out), "--resume")
    assert again.returncode == 0 and "no view to render" in again.stderr
    assert_same_dataset(out, reference_run)


def test_shards_merged_equal_an_unsharded_run(reference_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "dataset"
    assert run_module(*RUN_ARGS, "--out", str(out), "--shard", "1/2").returncode == 0
    assert sorted(path.name for path in out.glob("*.json")) == [
        "transforms_test.shard-1-of-2.json", "transforms_train.shard-1-of-2.json", "transforms_val.shard-1-of-2.json"]
    assert sorted(path.name for path in (out / "train").glob("*.png")) == sorted(
        f"r_{i}.png" for i in range(1, 24, 2))
    early = run_module("--merge", str(out))
    assert early.returncode == 2 and "shard 0/2 has not finished" in early.stderr
    mismatch = run_module(*[arg if arg != "3" else "4" for arg in RUN_ARGS], "--out", str(out), "--shard", "0/2")
    assert mismatch.returncode == 2 and "seed 3 there vs 4 now" in mismatch.stderr
    assert run_module(*RUN_ARGS, "--out", str(out), "--shard", "0/2").returncode == 0
    prior = out / "occupancy_prior.npz"
    prior.rename(out / "aside.npz")  # both shards wrote the same prior; the merge needs it there
    missing = run_module("--merge", str(out))
    assert missing.returncode == 2 and "occupancy_prior.npz is missing" in missing.stderr
    (out / "aside.npz").rename(prior)
    geometry = out / "scene_geometry.ply"
    geometry.rename(out / "aside.ply")
    missing = run_module("--merge", str(out))
    assert missing.returncode == 2 and "scene_geometry.ply is missing" in missing.stderr
    (out / "aside.ply").rename(geometry)
    merged = run_module("--merge", str(out))
    assert merged.returncode == 0, merged.stderr
    assert_same_dataset(out, reference_run)


def test_the_ngp_layout_holds_every_split_and_shards_write_it_too(tmp_path: Path) -> None:
    """--format ngp: one transforms.json beside nerf_synthetic's, from the same render, with every
    split's frames, their images and the shared intrinsics; a sharded run's merge writes it, and
    the COLMAP model (tests/test_colmap_format.py), too, the same as one run."""
    single = tmp_path / "single"
    formats = ["--format", "ngp", "--format", "colmap"]
    assert run_module(*RUN_ARGS, *formats, "--out", str(single)).returncode == 0
    ngp = json.loads((single / "transforms.json").read_text())
    splits = {split: load_split(single, split) for split in ("train", "val", "test")}
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x"):
        assert ngp[key] == splits["train"][key], key
    frames = [frame for split in ("train", "val", "test") for frame in splits[split]["frames"]]
    assert [f["transform_matrix"] for f in ngp["frames"]] == [f["transform_matrix"] for f in frames]
    assert [f["file_path"] for f in ngp["frames"]] == [f["file_path"].removeprefix("./") + ".png" for f in frames]
    assert all((single / f["file_path"]).is_file() for f in ngp["frames"])
    for split in ("train", "val", "test"):  # nerfstudio's split lists
        assert ngp[f"{split}_filenames"] == [f"{split}/r_{i}.png" for i in range(len(splits[split]["frames"]))]
    # Instant-NGP's cube (p * 0.33 + 0.5, side aabb_scale) holds the scene's bounds, and half of it would not.
    bounds = json.loads((single / "scene_profile.json").read_text())["bounds"]
    needed = 2 * 0.33 * max(abs(v) for v in bounds["min"] + bounds["max"])
    assert needed <= ngp["aabb_scale"] and (ngp["aabb_scale"] == 1 or needed > ngp["aabb_scale"] / 2)
    sharded = tmp_path / "sharded"
    for shard in ("0/2", "1/2"):
        assert run_module(*RUN_ARGS, *formats, "--out", str(sharded), "--shard", shard).returncode == 0
    # Only the merge knows every frame.
    assert not (sharded / "transforms.json").exists() and not (sharded / "colmap").exists()
    assert run_module("--merge", str(sharded)).returncode == 0
    assert_same_dataset(sharded, single)


def test_same_seed_same_dataset(reference_run: Path, tmp_path: Path) -> None:
    """A second run with the same flags and seed writes the same dataset (other seeds, other
    train/val poses: tests/test_trajectories.py)."""
    assert run_module(*RUN_ARGS, "--out", str(tmp_path / "again")).returncode == 0
    assert_same_dataset(tmp_path / "again", reference_run)


# --- depth and normals against analytic ray distances --------------------------------------


@pytest.fixture(scope="module")
def test_scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("run_scenes")
    result = subprocess.run([sys.executable, str(SCRIPTS / "make_scenes.py"), str(out), "sphere", "markers"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return out


def test_depth_is_the_analytic_ray_distance(test_scenes: Path, tmp_path: Path) -> None:
    """A sphere of radius 2 at (3, -2, 1), fitted into the NeRF frame, seen by a shifted
    landscape camera: Z = distance along each pixel-centre ray in NeRF units, A = 0 and Z = 0 off it."""
    scene = json.loads((test_scenes / "scenes.json").read_text())
    out = tmp_path / "dataset"
    result = run_module(str(test_scenes / "sphere.blend"), "--out", str(out), "--width", "64", "--height", "48",
                        "--shift-x", "0.05", "--train-views", "2", "--val-views", "0", "--test-views", "2",
                        "--samples", "4", "--depth-normals", "all", "--no-progress")
    assert result.returncode == 0, result.stderr
    checked = 0
    for split in ("train", "test"):
        document = load_split(out, split)
        assert document["depth_normals"]["background"].startswith("Z = 0 and A = 0")
        frame_record = document["world_to_nerf"]
        centre = np.asarray(frame_record["matrix"]) @ [*scene["sphere_centre"], 1.0]
        radius = scene["sphere_radius"] * frame_record["scale"]
        rows, columns = np.mgrid[0:document["h"], 0:document["w"]] + 0.5
        for frame in document["frames"]:
            pose = np.asarray(frame["transform_matrix"])
            directions = np.stack([(columns - document["cx"]) / document["fl_x"],
                                   -(rows - document["cy"]) / document["fl_y"], -np.ones_like(rows)], axis=-1)
            directions = directions / np.linalg.norm(directions, axis=-1, keepdims=True) @ pose[:3, :3].T
            offset = pose[:3, 3] - centre[:3]
            b = directions @ offset
            discriminant = b * b - (offset @ offset - radius * radius)
            distance = -b - np.sqrt(np.maximum(discriminant, 0.0))
            depth, normal = read_exr(out / frame["depth_file_path"]), read_exr(out / frame["normal_file_path"])
            # Where the ray meets the surface at less than ~70 degrees (faceting of the 128 x 64 UV
            # sphere is below 6e-4 of its radius; at grazing angles its depth error grows as 1/cos).
            facing = (discriminant > 0.12 * radius * radius) & (depth["A"] > 0.999)
            assert facing.sum() > 300
            np.testing.assert_allclose(depth["Z"][facing], distance[facing], atol=2e-3)
            surface = pose[:3, 3] + directions * distance[..., None]
            expected_normal = (surface - centre[:3]) / radius
            got = np.stack([normal[axis] for axis in "XYZ"], axis=-1)
            np.testing.assert_allclose(got[facing], expected_normal[facing], atol=2e-2)
            # Rays missing the sphere by more than 0.14 R (~4 px, beyond the 1.5 px pixel filter).
            background = discriminant < -0.3 * radius * radius
            assert (depth["A"][background] == 0).all() and (depth["Z"][background] == 0).all()
            assert (got[background] == 0).all()
            # Planar (Blender) depth would be off by up to 6 % in the corners: this must not be it.
            planar = distance * -(directions @ pose[:3, 2])  # the camera looks down its -Z axis
            assert np.abs(depth["Z"][facing] - planar[facing]).max() > 10 * 2e-3
            checked += 1
    assert checked == 4


# --- intrinsics and poses proven by markers in real renders, for every camera flag ---------

GENERATOR_MARKER_CASES = {
    "square": [],
    "portrait": ["--width", "48", "--height", "64"],
    "landscape": ["--width", "64", "--height", "48"],
    "vertical_fit": ["--width", "64", "--height", "48", "--sensor-fit", "VERTICAL", "--lens", "35"],
    "shifted": ["--width", "64", "--height", "48", "--shift-x", "0.08", "--shift-y", "-0.05"],
    "portrait_shift_horizontal_fit": ["--width", "48", "--height", "64", "--sensor-fit", "HORIZONTAL",
                                      "--shift-x", "0.05", "--shift-y", "0.1", "--sensor-width", "30"],
    "wide_pixels_at_half": ["--width", "128", "--height", "96", "--resolution-percentage", "50",
                            "--pixel-aspect", "2:1", "--shift-x", "0.04"],
}


@pytest.fixture(scope="module")
def marker_datasets(test_scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """All cases in one Blender process (generate_dataset in-process), as the add-on would call it."""
    out = tmp_path_factory.mktemp("marker_datasets")
    cases = []
    for name, flags in GENERATOR_MARKER_CASES.items():
        kwargs = {"out_dir": str(out / name), "blend_path": str(test_scenes / "markers.blend"),
                  "width": 48, "height": 48, "train_views": 3, "val_views": 0, "test_views": 2,
                  "samples": 16, "depth_normals": "none"}
        names = {"--width": "width", "--height": "height", "--sensor-fit": "sensor_fit", "--lens": "lens",
                 "--shift-x": "shift_x", "--shift-y": "shift_y", "--sensor-width": "sensor_width",
                 "--resolution-percentage": "resolution_percentage"}
        for flag, value in zip(flags[::2], flags[1::2]):
            if flag == "--pixel-aspect":
                kwargs["pixel_aspect"] = [float(part) for part in value.split(":")]
            else:
                kwargs[names[flag]] = value if flag == "--sensor-fit" else float(value)
        for key in ("width", "height", "resolution_percentage"):
            if key in kwargs:
                kwargs[key] = int(kwargs[key])
        cases.append({"name": name, "kwargs": kwargs})
    (out / "cases.json").write_text(json.dumps(cases))
    result = subprocess.run([sys.executable, str(SCRIPTS / "generate_cases.py"), str(out / "cases.json")],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert set(json.loads((out / "results.json").read_text()).values()) == {"ok"}
    return out


@pytest.mark.parametrize("case", sorted(GENERATOR_MARKER_CASES))
def test_markers_land_where_the_dataset_projects_them(marker_datasets: Path, test_scenes: Path, case: str) -> None:
    """Each emissive marker's coverage-weighted centroid is within 0.5 px of the projection of its
    Blender position through world_to_nerf, the frame's transform_matrix and the JSON intrinsics."""
    markers = json.loads((test_scenes / "scenes.json").read_text())["markers"]
    dataset = marker_datasets / case
    for split in ("train", "test"):
        document = load_split(dataset, split)
        to_nerf = np.asarray(document["world_to_nerf"]["matrix"])
        for frame in document["frames"]:
            with Image.open(dataset / (frame["file_path"] + ".png")) as image:
                pixels = np.asarray(image).astype(float)
            assert pixels.shape[:2] == (document["h"], document["w"])
            world_to_camera = np.linalg.inv(np.asarray(frame["transform_matrix"]))
            rows, columns = np.mgrid[0:document["h"], 0:document["w"]] + 0.5
            colour = pixels[..., :3].argmax(axis=-1)
            for channel, marker in enumerate(markers):
                x, y, z, _ = world_to_camera @ to_nerf @ [*marker, 1.0]
                u = document["cx"] + document["fl_x"] * x / -z
                v = document["cy"] - document["fl_y"] * y / -z
                assert 1 <= u <= document["w"] - 1 and 1 <= v <= document["h"] - 1, "the fit keeps markers in view"
                weights = np.where(colour == channel, pixels[..., 3], 0.0)
                assert weights.sum() > 0, f"marker {channel} not visible"
                centroid = ((weights * columns).sum() / weights.sum(), (weights * rows).sum() / weights.sum())
                assert centroid == (pytest.approx(u, abs=0.5), pytest.approx(v, abs=0.5)), (case, frame["file_path"])
    generator = load_split(dataset, "train")["generator"]
    assert generator["settings"]["camera"]["source"] == "flags"
    assert math.isclose(load_split(dataset, "train")["camera_angle_x"],
                        2 * math.atan(document["w"] / (2 * document["fl_x"])))
