"""Real-world .blend files: scenes built in code for each kind of trouble, and the three shared
scenes nobody here made (../shared/scenes).  Real bpy, real Cycles, tiny renders.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from test_datasets_gen import SCRIPTS, load_split, read_exr, require_blender, run_module

TINY = ["--resolution", "24", "--train-views", "3", "--val-views", "1", "--test-views", "2", "--samples", "4",
        "--no-progress"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("scenes")
    result = subprocess.run([sys.executable, str(SCRIPTS / "make_scenes.py"), str(out)],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    return out


def fingerprint(path: Path) -> tuple[str, int]:
    """Bytes and modification time: the user's file must never change."""
    return hashlib.sha256(path.read_bytes()).hexdigest(), path.stat().st_mtime_ns


def error_line(result: subprocess.CompletedProcess) -> str:
    """The one error line (Blender's own warnings on loading may precede it)."""
    assert result.returncode == 2, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("datasets_gen: error:")]
    assert len(errors) == 1, result.stderr
    return errors[0]


def check_json(result: subprocess.CompletedProcess) -> dict:
    """The profile `--check` prints (after whatever Blender printed on loading)."""
    assert result.returncode == 0, result.stderr[-2000:]
    text = result.stdout
    return json.loads(text[text.index("\n{\n") + 1:] if "\n{\n" in text else text)


def alpha(dataset: Path, file_path: str) -> np.ndarray:
    with Image.open(dataset / (file_path + ".png")) as image:
        return np.asarray(image)[..., 3]


# --- scenes with trouble, built in code ----------------------------------------------------


def test_missing_texture_is_refused_naming_the_file(scenes: Path, tmp_path: Path) -> None:
    out = tmp_path / "never"
    line = error_line(run_module(str(scenes / "missing_texture.blend"), "--out", str(out), *TINY))
    assert str(scenes / "textures" / "brick_diffuse.png") in line
    assert "material 'brick'" in line and "--allow-missing" in line
    assert not out.exists(), "nothing is written before the scene passes its checks"


def test_missing_texture_renders_magenta_with_allow_missing(scenes: Path, tmp_path: Path) -> None:
    out = tmp_path / "dataset"
    result = run_module(str(scenes / "missing_texture.blend"), "--out", str(out), "--allow-missing", *TINY)
    assert result.returncode == 0, result.stderr
    assert "rendering despite" in result.stderr
    generator = load_split(out, "train")["generator"]
    assert generator["allow_missing"] is True and generator["settings"]["allow_missing"] is True
    assert any("brick_diffuse.png" in problem for problem in generator["scene_checks"]["allowed"])
    profile = json.loads((out / "scene_profile.json").read_text())
    assert profile["checks"]["allowed"] == generator["scene_checks"]["allowed"]
    texture = next(t for t in profile["textures"] if t["name"] == "brick_diffuse.png")
    assert texture["missing"] is True and texture["size"] is None
    with Image.open(out / "train" / "r_0.png") as image:
        pixels = np.asarray(image).astype(float)
    covered = pixels[..., 3] == 255
    red, green, blue = (pixels[..., channel][covered].mean() for channel in range(3))
    assert red > 2 * green and blue > 2 * green, "a missing image renders magenta in Cycles"


def test_missing_library_is_refused_naming_it(scenes: Path, tmp_path: Path) -> None:
    line = error_line(run_module(str(scenes / "missing_library.blend"), "--out", str(tmp_path / "o"), *TINY))
    assert str(scenes / "library.blend") in line and "object 'LibraryCube'" in line
    assert "'//library.blend'" in line and "--allow-missing" in line


@pytest.mark.parametrize(("name", "named"), [("empty_only", ["Just an Empty"]),
                                             ("all_hidden", ["Hidden cube", "Cube in a hidden collection"])])
def test_nothing_to_render_is_refused_even_with_allow_missing(scenes: Path, tmp_path: Path, name: str,
                                                               named: list[str]) -> None:
    line = error_line(run_module(str(scenes / f"{name}.blend"), "--out", str(tmp_path / "o"), "--allow-missing",
                                 *TINY))
    assert "nothing to render" in line and str(scenes / f"{name}.blend") in line
    for object_name in named:
        assert object_name in line


def test_far_and_huge_scene_gives_the_unit_scene_dataset(scenes: Path, tmp_path: Path) -> None:
    """The same object at the origin at scale 1 and at (1e5, -2e5, 3e4) at scale 1000."""
    datasets = {}
    for name in ("unit", "far"):
        datasets[name] = tmp_path / name
        result = run_module(str(scenes / f"{name}.blend"), "--out", str(datasets[name]), *TINY)
        assert result.returncode == 0, result.stderr
    unit_profile, far_profile = (json.loads((datasets[name] / "scene_profile.json").read_text())
                                 for name in ("unit", "far"))
    for key in ("min", "max"):
        np.testing.assert_allclose(far_profile["bounds"][key], unit_profile["bounds"][key], atol=1e-6)
    assert far_profile["world_to_nerf"]["scale"] == pytest.approx(unit_profile["world_to_nerf"]["scale"] / 1000)
    # The far object's centre maps to where the unit object's does (both: the bounds' centre -> origin).
    far_frame = far_profile["world_to_nerf"]
    np.testing.assert_allclose(np.asarray(far_frame["matrix"]) @ [1e5, -2e5, 3e4, 1.0],
                               np.asarray(unit_profile["world_to_nerf"]["matrix"]) @ [0, 0, 0, 1.0], atol=1e-6)
    for split in ("train", "val", "test"):
        unit, far = load_split(datasets["unit"], split), load_split(datasets["far"], split)
        for unit_frame, far_frame in zip(unit["frames"], far["frames"], strict=True):
            # Blender holds the far camera in float32 at |x| ~ 2e5 (a 0.016 step), i.e. 1.4e-5 in the NeRF frame.
            np.testing.assert_allclose(far_frame["transform_matrix"], unit_frame["transform_matrix"], atol=5e-5)
            with Image.open(datasets["unit"] / (unit_frame["file_path"] + ".png")) as a, \
                    Image.open(datasets["far"] / (far_frame["file_path"] + ".png")) as b:
                difference = np.abs(np.asarray(a).astype(float) - np.asarray(b).astype(float))
            assert difference.mean() < 0.5, "images must be nearly equal (mean difference below half a level)"
        if split == "test":
            for unit_frame, far_frame in zip(unit["frames"], far["frames"]):
                z_unit = read_exr(datasets["unit"] / unit_frame["depth_file_path"])["Z"]
                z_far = read_exr(datasets["far"] / far_frame["depth_file_path"])["Z"]
                both = (z_unit > 0) & (z_far > 0)
                np.testing.assert_allclose(z_far[both], z_unit[both], atol=2e-3)


def test_eevee_filmic_scene_is_rendered_with_cycles_and_standard(scenes: Path, tmp_path: Path) -> None:
    blend = scenes / "eevee_filmic.blend"
    before = fingerprint(blend)
    out = tmp_path / "dataset"
    result = run_module(str(blend), "--out", str(out), *TINY)
    assert result.returncode == 0, result.stderr
    assert "rendered with Cycles instead" in result.stderr and "Filmic" in result.stderr
    generator = load_split(out, "train")["generator"]
    assert generator["engine"] == "CYCLES" and generator["view_transform"] == "Standard"
    assert (generator["look"], generator["exposure"], generator["gamma"]) == ("None", 0.0, 1.0)
    assert generator["film_transparent"] is True
    source = generator["source_settings"]
    assert source["engine"].startswith("BLENDER_EEVEE") and source["view_transform"] == "Filmic"
    assert source["exposure"] == 0.5 and source["gamma"] == pytest.approx(1.2) and source["film_transparent"] is False
    assert source["view_layers"] == ["ViewLayer", "Second layer"]
    notes = " ".join(generator["scene_checks"]["notes"])
    assert "BLENDER_EEVEE" in notes and "Filmic" in notes and "opaque film" in notes
    # The opaque film and the burnt-in stamp of the file are gone: corners are transparent.
    corners = alpha(out, "./train/r_0")[[0, 0, -1, -1], [0, -1, 0, -1]]
    assert (corners == 0).all()
    # Bounds: the viewport-hidden ball renders and counts, the render-hidden helper plane does not,
    # the excluded asset collection counts where its instance is (x from -2.5 to 2.5), not where it is.
    profile = json.loads((out / "scene_profile.json").read_text())
    assert profile["objects"] == ["Asset instance", "Cube", "Viewport-hidden ball"]
    assert profile["hidden_objects"] == ["Asset cube", "Helper plane"]
    sphere = profile["world_to_nerf"]["sphere_blender"]
    np.testing.assert_allclose(sphere["centre"], [0.0, 0.0, 0.0], atol=1e-6)
    assert sphere["radius"] == pytest.approx(float(np.linalg.norm([2.5, 0.5, 0.5])), rel=1e-6)
    np.testing.assert_allclose(profile["bounding_sphere"]["centre"], [0, 0, 0], atol=1e-9)
    assert fingerprint(blend) == before, "the user's .blend must never change"


def test_scene_camera_takes_lens_and_resolution_from_the_file(scenes: Path, tmp_path: Path) -> None:
    out = tmp_path / "dataset"
    result = run_module(str(scenes / "eevee_filmic.blend"), "--out", str(out), "--use-scene-camera",
                        "--train-views", "1", "--val-views", "0", "--test-views", "0", "--samples", "1",
                        "--no-progress")
    assert result.returncode == 0, result.stderr
    document = load_split(out, "train")
    assert (document["w"], document["h"]) == (64, 36)  # 1280 x 720 at 5 %
    assert document["fl_x"] == pytest.approx(64 * 50 / 36)
    assert document["generator"]["settings"]["camera"]["source"] == "scene camera"
    line = error_line(run_module("../shared/scenes/20_specular.blend", "--use-scene-camera", "--check"))
    assert "no active camera" in line


def test_open_scene_is_left_as_it_was(scenes: Path, tmp_path: Path) -> None:
    """The add-on's path: generate_dataset(scene=the open scene) restores everything it changed."""
    blend = scenes / "eevee_filmic.blend"
    before_file = fingerprint(blend)
    report = tmp_path / "report.json"
    result = subprocess.run([sys.executable, str(SCRIPTS / "open_scene_roundtrip.py"), str(blend),
                             str(tmp_path / "dataset"), str(report)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    states = json.loads(report.read_text())
    before, after = states["before"], states["after"]
    for key in before:
        assert after[key] == before[key], key
    assert before["render"]["engine"].startswith("BLENDER_EEVEE") and before["camera"] == "Camera"
    assert (tmp_path / "dataset" / "transforms_test.json").is_file()
    assert load_split(tmp_path / "dataset", "train")["generator"]["settings"]["scene"]["source"] == str(blend)
    assert fingerprint(blend) == before_file


# --- the three shared scenes nobody here made ---------------------------------------------

def test_shared_a_blend_renders_framed_after_its_checks(tmp_path: Path, shared_scenes: Path) -> None:
    blend = shared_scenes / "A.blend"
    before = fingerprint(blend)
    out = tmp_path / "dataset"
    result = run_module("../shared/scenes/A.blend", "--out", str(out), *TINY)
    assert result.returncode == 0, result.stderr
    assert "BLENDER_EEVEE" in result.stderr and "rendered with Cycles" in result.stderr
    profile = json.loads((out / "scene_profile.json").read_text())
    assert profile["objects"] == ["Cube", "Suzanne", "Torus"]
    assert profile["world_to_nerf"]["rule"].startswith("fit:")
    material = {m["name"]: m for m in profile["materials"]}
    assert material["Material"]["view_dependent"] and not material["(no material)"]["view_dependent"]
    for split in ("train", "val", "test"):
        for frame in load_split(out, split)["frames"]:
            a = alpha(out, frame["file_path"])
            assert (a > 0).mean() > 0.05, "the object must fill a fair part of the view"
            border = np.concatenate([a[0], a[-1], a[:, 0], a[:, -1]])
            assert border.max() == 0, "the fit keeps the object off the image border"
    assert fingerprint(blend) == before


def test_shared_20_specular_profile_flags_its_spheres(shared_scenes: Path) -> None:
    profile = check_json(run_module("../shared/scenes/20_specular.blend", "--check"))
    assert profile["view_dependent"] is True and profile["transparency"] is True
    assert len(profile["objects"]) == 14
    spheres = [m for m in profile["materials"] if any(name.startswith("Sphere") for name in m["objects"])]
    assert len(spheres) == 14 and all(m["view_dependent"] for m in spheres)
    assert any("specular" in reason for m in spheres for reason in m["reasons"])


def test_shared_robot_is_refused_then_rendered_with_allow_missing(tmp_path: Path, shared_scenes: Path) -> None:
    line = error_line(run_module("../shared/scenes/RobotExpressive.blend", "--out", str(tmp_path / "o"), *TINY))
    assert "Texture.png" in line and "missing image file" in line and "--allow-missing" in line
    out = tmp_path / "dataset"
    result = run_module("../shared/scenes/RobotExpressive.blend", "--out", str(out), "--allow-missing", *TINY)
    assert result.returncode == 0, result.stderr
    generator = load_split(out, "test")["generator"]
    assert generator["allow_missing"] and any("Texture.png" in p for p in generator["scene_checks"]["allowed"])
    profile = json.loads((out / "scene_profile.json").read_text())
    # Its materials have a Cycles-only output with a Diffuse BSDF (the active output is EEVEE's).
    assert profile["view_dependent"] is False
    assert (alpha(out, "./test/r_0") > 0).mean() > 0.05


@pytest.mark.blender_binary
def test_both_entry_points_give_the_same_dataset(tmp_path: Path, shared_scenes: Path) -> None:
    """`python -m datasets_gen A.blend` and `blender -b A.blend --python generate.py -- ...`."""
    blender = require_blender()
    module_out, binary_out = tmp_path / "module", tmp_path / "binary"
    assert run_module("../shared/scenes/A.blend", "--out", str(module_out), *TINY).returncode == 0
    result = subprocess.run(
        [blender, "-b", str(shared_scenes / "A.blend"), "--python",
         str(Path(__file__).resolve().parents[1] / "datasets_gen" / "generate.py"), "--", "--out", str(binary_out),
         *TINY], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    for split in ("train", "val", "test"):
        module, binary = load_split(module_out, split), load_split(binary_out, split)
        assert binary["generator"].pop("blender_version") != module["generator"].pop("blender_version")
        for frame, reference in zip(binary.pop("frames"), module.pop("frames"), strict=True):
            assert frame.keys() == reference.keys() and frame["file_path"] == reference["file_path"]
            np.testing.assert_allclose(frame["transform_matrix"], reference["transform_matrix"], atol=1e-6)
            # Blender 3.4 and 5.0 shade differently (Principled BSDF v1 vs v2) but see the same geometry;
            # at 4 samples a pixel's coverage is noisy, so compare the masks and the total coverage.
            a, b = alpha(binary_out, frame["file_path"]) / 255.0, alpha(module_out, frame["file_path"]) / 255.0
            assert ((a > 0.5) != (b > 0.5)).mean() < 0.03 and abs(a.mean() - b.mean()) < 0.01
        assert binary == module
    assert json.loads((binary_out / "scene_profile.json").read_text()) == \
        json.loads((module_out / "scene_profile.json").read_text())
