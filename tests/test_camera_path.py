"""Camera animations: the path's maths (pure), a Blender camera animated along a known path
(real bpy: parent, keyed rotation, animated lens), the command line with Cycles frames, and
the backend's video render with its per-frame comparison, video file and resume."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REPO_ROOT, camera_path_through_test_views, run_python

from datasets_gen.core.camera_path import FrameCamera, camera_path_document, camera_to_nerf, parse_frames
from datasets_gen.core.intrinsics import CameraSettings
from datasets_gen.core.options import DatasetGenError
from nerf_backend.core.errors import DatasetError
from nerf_backend.core.video import video_info, write_video
from nerf_backend.data.dataset import load_camera_animation
from nerf_backend.data.run_folder import RunFolder
from nerf_backend.evaluation.animation import render_animation
from nerf_backend.evaluation.evaluate import evaluate_run

CPU = torch.device("cpu")
SCRIPT = REPO_ROOT / "tests" / "blender_scripts" / "animated_camera.py"
WORLD_TO_NERF = {"scale": 0.5, "translation": [0.1, -0.2, 0.3]}


# --- pure ------------------------------------------------------------------------------------

def test_frame_ranges_include_both_ends_and_refuse_nonsense():
    assert list(parse_frames("1:5")) == [1, 2, 3, 4, 5]
    assert list(parse_frames("-2:7:3")) == [-2, 1, 4, 7]
    for bad in ("1-5", "5:1", "1:5:0", "a:b", ""):
        with pytest.raises(DatasetGenError, match="--frames"):
            parse_frames(bad)


def test_camera_mapping_applies_the_datasets_similarity_and_drops_object_scale():
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    matrix = np.eye(4)
    matrix[:3, :3] = rotation * 3.0  # a camera object scaled 3×: only its rotation counts
    matrix[:3, 3] = [1.0, 2.0, 3.0]
    mapped = np.array(camera_to_nerf(matrix.tolist(), WORLD_TO_NERF))
    np.testing.assert_allclose(mapped[:3, :3], rotation, atol=1e-12)
    np.testing.assert_allclose(mapped[:3, 3], [0.6, 0.8, 1.8], atol=1e-12)
    with pytest.raises(DatasetGenError, match="not a camera pose"):
        camera_to_nerf([[0.0] * 4] * 4, WORLD_TO_NERF)


def test_each_frame_keeps_its_own_lens_and_a_path_keeps_one_size():
    pose = np.eye(4).tolist()
    frames = [FrameCamera(f, pose, CameraSettings(lens_mm=lens, resolution_x=80, resolution_y=60))
              for f, lens in ((1, 25.0), (2, 50.0))]
    document = camera_path_document("cam", frames, WORLD_TO_NERF, fps=24.0, cycles=True)
    assert [round(f["fl_x"], 6) for f in document["frames"]] == [round(25 * 80 / 36, 6), round(50 * 80 / 36, 6)]
    assert document["frames"][1]["cycles_file_path"] == "cycles/0002.png"
    bigger = FrameCamera(3, pose, CameraSettings(resolution_x=100, resolution_y=60))
    with pytest.raises(DatasetGenError, match="image size changes"):
        camera_path_document("cam", [*frames, bigger], WORLD_TO_NERF, fps=24.0)


def test_videos_pad_odd_sizes_and_keep_the_frame_rate(tmp_path):
    frames = [np.full((31, 41, 3), value, np.uint8) for value in (0, 80, 160, 240, 255)]
    path = write_video(tmp_path / "odd.mp4", frames, fps=30000 / 1001)
    info = video_info(path)
    assert (info["frames"], info["width"], info["height"]) == (5, 42, 32)
    assert info["fps"] == pytest.approx(29.97, abs=0.01)
    assert not list(tmp_path.glob(".*partial"))


# --- a known animation in real Blender -----------------------------------------------------

def test_a_blender_camera_animated_along_a_known_path_gives_its_poses_and_lens(tmp_path):
    dataset = tmp_path / "dataset"
    dataset.mkdir()
    (dataset / "transforms_train.json").write_text(json.dumps({"world_to_nerf": WORLD_TO_NERF}))
    out = tmp_path / "path"
    result = subprocess.run([sys.executable, str(SCRIPT), str(REPO_ROOT), str(dataset), str(out)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "frame after export: 3 percentage: 50" in result.stdout  # the scene is left as it was
    document = json.loads((out / "camera_path.json").read_text())
    assert document["fps"] == pytest.approx(30 / 1.001)
    assert [f["frame"] for f in document["frames"]] == [1, 3, 5]
    for entry in document["frames"]:
        f = entry["frame"]
        turn, tilt = math.radians(10.0 * f), math.radians(90.0)
        rz = np.array([[math.cos(turn), -math.sin(turn), 0], [math.sin(turn), math.cos(turn), 0], [0, 0, 1]])
        rx = np.array([[1, 0, 0], [0, math.cos(tilt), -math.sin(tilt)], [0, math.sin(tilt), math.cos(tilt)]])
        pose = np.array(entry["transform_matrix"])
        np.testing.assert_allclose(pose[:3, :3], rz @ rx, atol=1e-6)  # Blender's XYZ Euler: Rz·Ry·Rx
        world = np.array([f, 0.0, 0.0]) + np.array([0.0, -4.0, 1.0])
        np.testing.assert_allclose(pose[:3, 3], 0.5 * world + np.array([0.1, -0.2, 0.3]), atol=1e-6)
        assert (entry["w"], entry["h"]) == (32, 24)
        assert entry["lens_mm"] == pytest.approx(20.0 + 5.0 * f)
        assert entry["fl_x"] == pytest.approx((20.0 + 5.0 * f) * 32 / 36, rel=1e-6)
        assert (entry["cx"], entry["cy"]) == (16.0, 12.0)


# --- the command line with Cycles, and the backend's video ----------------------------------

@pytest.fixture(scope="module")
def turntable_path(tiny_demo_dataset, tmp_path_factory) -> Path:
    """The demo's turntable camera, frames 1, 17 and 33 at 5 % of 800×600, with Cycles' frames,
    mapped into (a copy of) the tiny demo dataset's frame."""
    dataset = tmp_path_factory.mktemp("path_dataset") / "dataset"
    dataset.mkdir()
    shutil.copy(tiny_demo_dataset / "transforms_train.json", dataset)
    result = run_python("-m", "datasets_gen", "--demo", "--out", str(dataset), "--camera-path", "turntable camera",
                        "--frames", "1:48:16", "--with-cycles", "--resolution-percentage", "5", "--no-progress")
    path = dataset / "camera_paths" / "turntable_camera" / "camera_path.json"
    assert f"wrote {path}" in result.stderr
    return path


def test_the_command_line_writes_the_path_and_keeps_its_cycles_frames(turntable_path):
    document = json.loads(turntable_path.read_text())
    assert [f["frame"] for f in document["frames"]] == [1, 17, 33]
    assert [f["lens_mm"] for f in document["frames"]] == pytest.approx(
        [35.0 + 15.0 * (0.5 - 0.5 * math.cos(2 * math.pi * (f - 1) / 48)) for f in (1, 17, 33)])
    cycles = sorted((turntable_path.parent / "cycles").glob("*.png"))
    assert [p.name for p in cycles] == ["0001.png", "0017.png", "0033.png"]
    stamps = [p.stat().st_mtime_ns for p in cycles]
    dataset = turntable_path.parents[2]
    again = run_python("-m", "datasets_gen", "--demo", "--out", str(dataset), "--camera-path", "turntable camera",
                       "--frames", "1:48:16", "--with-cycles", "--resolution-percentage", "5", "--no-progress")
    assert "kept 3 Cycles frames" in again.stdout + again.stderr
    assert [p.stat().st_mtime_ns for p in cycles] == stamps
    other = run_python("-m", "datasets_gen", "--demo", "--out", str(dataset), "--camera-path", "turntable camera",
                       "--frames", "1:48:24", "--resolution-percentage", "5", "--no-progress", check=False)
    assert other.returncode == 2 and "a different camera path is there" in other.stderr
    assert "--overwrite" in other.stderr and [p.stat().st_mtime_ns for p in cycles] == stamps
    missing = run_python("-m", "datasets_gen", "--demo", "--out", str(dataset), "--camera-path", "no such camera",
                         "--no-progress", check=False)
    assert missing.returncode == 2 and "'no such camera'" in missing.stderr and "turntable camera" in missing.stderr


def test_the_backend_renders_the_path_as_frames_and_videos_beside_cycles(trained_run, turntable_path, tmp_path):
    out = tmp_path / "animation"
    result = run_python("-m", "nerf_backend", "render", str(trained_run), "--camera-path", str(turntable_path),
                        "--cycles", "--out", str(out), "--no-progress")
    assert "rendered 3 frames at 40×30" in result.stdout and "against Cycles: PSNR" in result.stdout
    assert sorted(p.name for p in (out / "frames").glob("*.png")) == ["0001.png", "0017.png", "0033.png"]
    assert video_info(out / "nerf.mp4") == {"frames": 3, "width": 40, "height": 30, "fps": 24.0}
    assert video_info(out / "side_by_side.mp4") == {"frames": 3, "width": 120, "height": 30, "fps": 24.0}
    metrics = json.loads((out / "frame_metrics.json").read_text())
    assert [f["frame"] for f in metrics["frames"]] == [1, 17, 33]
    psnrs = [f["psnr"] for f in metrics["frames"]]
    assert metrics["mean"]["psnr"] == pytest.approx(np.mean(psnrs))
    assert min(psnrs) > 12.0  # a 250-step preview NeRF seen from a new, closer camera: far above a blank image
    assert (out / "frame_metrics.png").stat().st_size > 1000


def test_per_frame_scores_are_evals_own_on_the_test_views_and_resume_keeps_frames(trained_run, tmp_path):
    """A camera path through the test views, with the dataset's test images as its 'Cycles'
    frames, must score exactly as ``eval`` scores those views."""
    dataset = Path(RunFolder(trained_run).read_config()["dataset"])
    path, _, _ = camera_path_through_test_views(dataset, tmp_path / "path")
    out = tmp_path / "out"
    record = render_animation(RunFolder(trained_run), path, CPU, out, cycles=True, progress=False)
    metrics = evaluate_run(trained_run, "test", CPU, progress=False)
    ours = json.loads((out / "frame_metrics.json").read_text())["frames"]
    assert [f["psnr"] for f in ours] == pytest.approx([v["psnr"] for v in metrics["per_view"]], abs=1e-6)
    assert [f["ssim"] for f in ours] == pytest.approx([v["ssim"] for v in metrics["per_view"]], abs=1e-6)
    assert record["seconds_per_frame"] is not None

    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "frames").glob("*.png")}
    again = render_animation(RunFolder(trained_run), path, CPU, out, progress=False)
    assert again["seconds_per_frame"] == record["seconds_per_frame"]  # nothing rendered again
    assert {p.name: p.stat().st_mtime_ns for p in (out / "frames").glob("*.png")} == stamps

    (out / "frames" / "0002.png").unlink()  # an interrupted render: only the missing frame is drawn
    render_animation(RunFolder(trained_run), path, CPU, out, progress=False)
    assert (out / "frames" / "0002.png").is_file()
    assert {n: s for n, s in stamps.items() if n != "0002.png"} == {
        p.name: p.stat().st_mtime_ns for p in (out / "frames").glob("*.png") if p.name != "0002.png"}

    document = json.loads(path.read_text())
    document["frames"][0]["transform_matrix"][0][3] += 0.1  # another path: every frame is rendered again
    path.write_text(json.dumps(document))
    render_animation(RunFolder(trained_run), path, CPU, out, progress=False)
    assert all(p.stat().st_mtime_ns != stamps[p.name] for p in (out / "frames").glob("*.png"))


def test_bad_camera_paths_are_named(tmp_path):
    path = tmp_path / "camera_path.json"
    frame = {"frame": 1, "transform_matrix": np.eye(4).tolist(), "w": 8, "h": 6, "fl_x": 5, "fl_y": 5, "cx": 4, "cy": 3}
    for document, message in (
        ({"frames": [frame]}, "'fps'"),
        ({"fps": 24, "frames": [{**frame, "fl_x": None}]}, "fl_x"),
        ({"fps": 24, "frames": [{k: v for k, v in frame.items() if k != "cy"}]}, "missing 'cy'"),
        ({"fps": 24, "frames": [frame, frame]}, "frame 1 is listed twice"),
        ({"fps": 24, "frames": [frame, {**frame, "frame": 2, "w": 10}]}, "differ in size"),
        ({"fps": 24, "frames": [{**frame, "cycles_file_path": "../x.png"}]}, "outside"),
    ):
        path.write_text(json.dumps(document))
        with pytest.raises(DatasetError, match=message) as error:
            load_camera_animation(path)
        assert str(path) in str(error.value)
