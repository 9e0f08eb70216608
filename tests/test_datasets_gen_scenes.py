"""Real-world .blend files: scenes built in code for each kind of trouble, and the three shared
scenes nobody here made (../shared/scenes).  Real bpy, real Cycles, tiny renders.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from conftest import run_python
from PIL import Image
from test_datasets_gen import SCRIPTS, load_split, read_exr, require_blender, run_module

from datasets_gen.core.trajectories import RIG_RADIUS

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


# --- issue 7: the same object at any scale and place gives the same dataset --------------------
# make_scenes.PLACEMENTS: "unit" (scale 1 at the origin), "tiny" (scale 1e-3), "huge" (scale 1e4),
# "far" (scale 1, 1e5 units from the origin) and "far_huge" (scale 1e4 at (1e5, -2e5, 3e4)).
PLACED = ("tiny", "huge", "far", "far_huge")
#: Training for the PSNR comparison: the fast preset, briefly, with one seed.
PSNR_ITERS = 200
#: Measured at 200 iterations, seed 0 (Blender 5.0.1, torch CPU): unit 20.979 dB; tiny -0.005,
#: huge -0.013, far -0.169, far_huge -0.039 dB from it.  Seed 1: unit 19.734, far +0.022: the
#: far dataset's float32 perturbations (0.7 levels, 0.003 in poses) move training by a few tenths
#: at most, while another seed moves it by 1.2 dB.  0.5 dB is ~3x the largest measured difference.
PSNR_MARGIN_DB = 0.5


@pytest.fixture(scope="module")
def placed(scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], Path]:
    """name -> the dataset of make_scenes' placed object NAME, rendered once with the TINY settings."""
    out = tmp_path_factory.mktemp("placed")

    @functools.cache
    def dataset(name: str) -> Path:
        result = run_module(str(scenes / f"{name}.blend"), "--out", str(out / name), *TINY)
        assert result.returncode == 0, result.stderr
        return out / name

    return dataset


def float32_step(profile: dict) -> float:
    """Blender's float32 step at the largest |coordinate| of the scene and its cameras, in NeRF units.

    Blender holds object and camera matrices in float32.  Every dataset camera is RIG_RADIUS (NeRF
    units) from the bounding sphere's centre, farther than any vertex, so no coordinate exceeds
    max|centre| + RIG_RADIUS / scale; one float32 step there, times the frame's scale, is `e`.
    """
    frame = profile["world_to_nerf"]
    extent = max(abs(c) for c in frame["sphere_blender"]["centre"]) + RIG_RADIUS / frame["scale"]
    return frame["scale"] * float(np.spacing(np.float32(extent)))


@pytest.mark.parametrize("name", PLACED)
def test_scaled_or_far_scene_gives_the_unit_scene_dataset(scenes: Path, placed: Callable[[str], Path],
                                                          name: str) -> None:
    """Issue 7: the object at scale 1e-3, 1e4, 1e5 units away gives the unit scene's dataset.

    Tolerances come from float32 in Blender.  `e` (float32_step) is one float32 step at the scenes'
    coordinates in NeRF units, summed over the two datasets compared: 8.5e-7 (tiny), 7.8e-7 (huge),
    1.8e-6 (far_huge: |x| up to 2.4e5, a 2**-6 step times scale 9e-5) and 0.0070 (far: |x| up to
    66671, in [2**16, 2**17), a 2**-7 = 0.0078 step times scale 0.899), so the first three must
    match to ~1e-6 and "far" only to its float32 steps.  Measured on Blender 5.0.1 (max over the
    six views), tiny / huge / far_huge: poses 1.5e-7 / 1.3e-7 / 8.3e-7 (allowed 4.2e-7 / 3.9e-7 /
    9.2e-7), bounds 8e-9, scale ratios within 5e-8 of nominal, identical PNGs, depth 2.2e-6 /
    2.4e-6 / 3.8e-6 (allowed 1.4e-5 / 1.4e-5 / 2.0e-5).  far: poses 0.0032 (allowed 0.0035),
    bounds 6.6e-4 (0.019), scale ratio 1 + 1.0e-3 (0.0099), mean image difference 0.69 levels
    (allowed 5.2), depth median <= 0.0034 and 97.8 % of pixels within the allowed 0.0365 (the rest
    grazing or occluding-edge pixels, up to 0.044).
    """
    unit, case = placed("unit"), placed(name)
    offset, scale = (json.loads((scenes / "scenes.json").read_text())["placements"][name][key]
                     for key in ("offset", "scale"))
    unit_profile, case_profile = (json.loads((path / "scene_profile.json").read_text()) for path in (unit, case))
    unit_frame, case_frame = unit_profile["world_to_nerf"], case_profile["world_to_nerf"]
    e = float32_step(unit_profile) + float32_step(case_profile)
    target = case_frame["target_radius"]
    assert unit_frame["target_radius"] == target

    # The frame is fitted to the vertices Blender holds: each part's float32 world matrix moves its
    # vertices by <= e/2 per axis, so the bounds' centre moves by <= e/2 per axis and the bounding
    # radius by <= sqrt(3) e (NeRF units): the scale by a factor within sqrt(3) e / target_radius of the
    # nominal one, and a bound by <= e/2 + e/2 + sqrt(3) e (the radius error times |bound - centre|
    # <= radius).
    assert case_frame["scale"] / unit_frame["scale"] == pytest.approx(1.0 / scale,
                                                                    rel=math.sqrt(3) * e / target + 1e-12)
    frame_atol = (1.0 + math.sqrt(3)) * e + 1e-9
    for key in ("min", "max"):
        np.testing.assert_allclose(case_profile["bounds"][key], unit_profile["bounds"][key], atol=frame_atol)
    # The placing Empty's origin maps to where the unit object's origin does.
    np.testing.assert_allclose(np.asarray(case_frame["matrix"]) @ [*offset, 1.0],
                               np.asarray(unit_frame["matrix"]) @ [0.0, 0.0, 0.0, 1.0], atol=frame_atol)

    for split in ("train", "val", "test"):
        unit_split, case_split = load_split(unit, split), load_split(case, split)
        # The dataset camera's clipping scales with the scene (0.05 and 100 NeRF units): nothing
        # is clipped at 1e-3 or 1e4, and the clip range is the same in the NeRF frame.
        np.testing.assert_allclose(np.asarray(case_split["generator"]["camera"]["clip"]) * case_frame["scale"],
                                   np.asarray(unit_split["generator"]["camera"]["clip"]) * unit_frame["scale"],
                                   rtol=1e-6)
        pixel = RIG_RADIUS / unit_split["fl_x"]  # a pixel's footprint at the object, NeRF units
        for unit_view, case_view in zip(unit_split["frames"], case_split["frames"], strict=True):
            # Poses: a camera's position is the protocol's, inverse-mapped into Blender's world and
            # rounded to float32 there: <= e/2 per axis, both datasets together.  Rotations do not
            # depend on scale or place (measured: equal); 1e-6 leaves room for Blender's float32
            # decomposition of the matrix it is given.
            a, b = np.asarray(unit_view["transform_matrix"]), np.asarray(case_view["transform_matrix"])
            np.testing.assert_allclose(b[:3, :3], a[:3, :3], atol=1e-6)
            np.testing.assert_allclose(b[:3, 3], a[:3, 3], atol=e / 2 + 1e-9)
            np.testing.assert_array_equal(b[3], a[3])
            # Images: relative to the object, the camera is off by <= sqrt(3)/2 e (its rounding) +
            # sqrt(3)/2 e (the fitted centre) + sqrt(3) e (the fitted scale, over the <= target radius
            # to the silhouette) and each surface by <= sqrt(3) e (its matrix, then Cycles' float32
            # transform): 3 sqrt(3) e in all, a silhouette shift of s = 3 sqrt(3) e / pixel.  Only
            # silhouette pixels (partly covered in the unit image, a fraction f of the image) change
            # by more than noise, each by ~255 s levels at most: mean |difference| <= 0.5 + 255 s f.
            with Image.open(unit / (unit_view["file_path"] + ".png")) as image:
                unit_pixels = np.asarray(image).astype(float)
            with Image.open(case / (case_view["file_path"] + ".png")) as image:
                case_pixels = np.asarray(image).astype(float)
            silhouette = ((unit_pixels[..., 3] > 0) & (unit_pixels[..., 3] < 255)).mean()
            shift = 3 * math.sqrt(3) * e / pixel
            assert np.abs(case_pixels - unit_pixels).mean() <= 0.5 + 255 * shift * silhouette, \
                f"{name} {case_view['file_path']}: images must be nearly equal (8-bit levels)"
            if split != "test":
                continue
            # Depth (NeRF units): a surface facing the camera moves along the ray by no more than
            # the camera and the surface relative to each other, 3 sqrt(3) e as above, plus 1e-5 for
            # Cycles' own float32 ray distances (~4.8e-7 a step at depths 4-6: measured <= 8 steps).
            # At grazing angles and occluding edges a sub-pixel shift changes depth by more, so 95 %
            # of the pixels both datasets hit must be within it.
            z_unit = read_exr(unit / unit_view["depth_file_path"])["Z"]
            z_case = read_exr(case / case_view["depth_file_path"])["Z"]
            both = (z_unit > 0) & (z_case > 0)
            assert both.sum() >= 0.95 * max((z_unit > 0).sum(), (z_case > 0).sum())
            within = np.abs(z_case[both] - z_unit[both]) <= 3 * math.sqrt(3) * e + 1e-5
            assert within.mean() >= 0.95, f"{name} {case_view['depth_file_path']}: depth differs"


@pytest.fixture(scope="module")
def placed_psnr(placed: Callable[[str], Path], tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], float]:
    """name -> test PSNR of the fast preset trained PSNR_ITERS iterations (seed 0) on that dataset."""
    runs = tmp_path_factory.mktemp("placed_runs")

    @functools.cache
    def psnr(name: str) -> float:
        run = runs / name
        run_python("-m", "nerf_backend", "train", str(placed(name)), "--preset", "fast", "--out", str(run),
                   "--iters", str(PSNR_ITERS), "--seed", "0", "--no-progress")
        run_python("-m", "nerf_backend", "eval", str(run), "--no-progress")
        return json.loads((run / "metrics.json").read_text())["psnr"]

    return psnr


@pytest.mark.slow
@pytest.mark.parametrize("name", PLACED)
def test_scaled_or_far_scene_trains_to_the_unit_scene_psnr(placed_psnr: Callable[[str], float], name: str) -> None:
    """Issue 7's "same PSNR": the backend sees only the NeRF-frame dataset, so the same seed gives
    the same training (a rerun on one dataset gives the same PSNR to the last bit).  "tiny", "huge"
    and "far_huge" datasets differ from the unit one by ~1e-7 in their poses only, "far" by float32
    steps at 1e5 (see the test above); see PSNR_MARGIN_DB for the measured differences.  Five
    trainings of 200 iterations on 3 views at 24x24: 1-3 minutes each on 2 busy cores, hence slow.
    """
    print(f"{name}: {placed_psnr(name):.3f} dB, unit scene {placed_psnr('unit'):.3f} dB")
    assert placed_psnr(name) == pytest.approx(placed_psnr("unit"), abs=PSNR_MARGIN_DB)


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


def test_a_flat_scene_gets_bounds_with_a_thickness_the_backend_takes(tmp_path: Path) -> None:
    """A single plane (no extent along z): the profile's bounds are widened across it to
    MIN_THICKNESS of their longest side, which the backend reads as a box; before, min equalled
    max on z and training refused the dataset."""
    from datasets_gen.core.frame_fit import MIN_THICKNESS
    from nerf_backend.data.dataset import load_scene_bounds
    result = subprocess.run([sys.executable, str(SCRIPTS / "make_scenes.py"), str(tmp_path), "flat"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    out = tmp_path / "dataset"
    assert run_module(str(tmp_path / "flat.blend"), "--out", str(out), *TINY).returncode == 0
    bounds = json.loads((out / "scene_profile.json").read_text())["bounds"]
    sides = [hi - lo for lo, hi in zip(bounds["min"], bounds["max"])]
    assert sides[0] == pytest.approx(sides[1], rel=1e-6)  # the square card, fitted to the protocol's frame
    assert sides[2] == pytest.approx(MIN_THICKNESS * sides[0], rel=1e-6)
    assert bounds["min"][2] == pytest.approx(-bounds["max"][2], abs=1e-9)  # about the card's plane
    box = load_scene_bounds(out)
    assert box is not None and all(lo < hi for lo, hi in zip(box.box_min, box.box_max))


def test_material_facts_are_read_from_the_node_trees(tmp_path: Path) -> None:
    """What each sphere of materials.blend is made of, in its scene profile: constants read from
    the Principled BSDF, a texture's and a node group's inputs named as the reason they vary."""
    result = subprocess.run([sys.executable, str(SCRIPTS / "make_scenes.py"), str(tmp_path), "materials"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    profile = check_json(run_module(str(tmp_path / "materials.blend"), "--check"))
    facts = {m["name"]: m["appearance"] for m in profile["materials"]}
    assert {m["name"]: m["objects"] for m in profile["materials"]}["Metal"] == ["MetalBall"]
    glass, metal, film = (facts[name]["inputs"] for name in ("Glass", "Metal", "Film"))
    assert glass["transmission"] == {"value": 1.0} and glass["roughness"] == {"value": 0.0}
    assert glass["ior"] == {"value": 1.5}
    # No emission: a new Principled BSDF's colour is white and its strength 0 (Blender 4+).
    assert len(glass["emission_colour"]["value"]) == 3 and glass["emission_strength"] == {"value": 0.0}
    assert metal["metallic"] == {"value": 1.0}
    assert metal["roughness"] == {"varies": "driven by the Noise Texture node 'Scratches'"}  # through a reroute
    assert film["thin_film_thickness"] == {"value": 500.0} and film["thin_film_ior"] == {"value": 1.33}
    assert film["roughness"] == {"value": 0.1}
    grouped = facts["Grouped"]["inputs"]
    assert grouped["roughness"] == {"varies": "driven by a node group's input"} and grouped["coat"] == {"value": 0.8}
    assert facts["Mixed"]["other_shaders"] == ["glossy BSDF 'Sheen layer'", "mix shader 'Mix Shader'"]
    assert facts["Mixed"]["inputs"]["roughness"] == {"value": 0.2}
    assert facts["Chalk"] == {"shader": "other", "inputs": {}, "other_shaders": ["diffuse BSDF 'Diffuse BSDF'"]}


def test_each_material_s_region_is_in_the_profile_and_in_the_prior_s_cells(tmp_path: Path) -> None:
    """materials.blend's six balls (glass, metal, thin film, a coated group, glossy, chalk), a
    ball a material: each material's appearance region with why in the profile, and the prior's
    ``regions`` holding it on every point of its ball's surface."""
    from nerf_contract.dataset_layout import APPEARANCE_REGIONS
    result = subprocess.run([sys.executable, str(SCRIPTS / "make_scenes.py"), str(tmp_path), "materials"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    out = tmp_path / "dataset"
    assert run_module(str(tmp_path / "materials.blend"), "--out", str(out), *TINY).returncode == 0
    profile = json.loads((out / "scene_profile.json").read_text())
    regions = {m["name"]: m["region"] for m in profile["materials"]}
    assert regions == {"Glass": "transmissive", "Metal": "metal", "Film": "thin_film", "Grouped": "glossy",
                       "Mixed": "glossy", "Chalk": "diffuse"}
    reasons = {m["name"]: m["region_reason"] for m in profile["materials"]}
    assert reasons["Glass"] == "transmission 1" and reasons["Film"] == "thin film 500 nm"
    with np.load(out / profile["occupancy_prior"]["file"]) as data:
        cells, surface = data["regions"], data["surface"]
        box_min, cell_size = data["box_min"], float(data["cell_size"])
    assert np.array_equal(cells > 0, surface)
    matrix = np.array(profile["world_to_nerf"]["matrix"])
    generator = np.random.default_rng(0)
    for index, name in enumerate(("Glass", "Metal", "Film", "Grouped", "Mixed", "Chalk")):
        directions = generator.normal(size=(500, 3))
        # Between the 16×8 sphere's faces (0.36-0.40 from its centre) and its vertices.
        world = np.array([1.0 * index - 2.5, 0.0, 0.0]) + 0.38 * directions / np.linalg.norm(directions, axis=1,
                                                                                            keepdims=True)
        nerf = world @ matrix[:3, :3].T + matrix[:3, 3]
        held = cells[tuple(np.floor((nerf - box_min) / cell_size).astype(int).T)]
        assert (held == APPEARANCE_REGIONS.index(regions[name])).all(), (name, np.unique(held))
    shares = profile["occupancy_prior"]["regions"]
    assert set(shares) == set(regions.values()) and abs(sum(shares.values()) - 1.0) < 1e-9


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
    binary_profile = json.loads((binary_out / "scene_profile.json").read_text())
    module_profile = json.loads((module_out / "scene_profile.json").read_text())
    # Debian's Blender has no numpy: no occupancy prior nor scene geometry, and the profile says why.
    for key in ("occupancy_prior", "geometry"):
        assert binary_profile.pop(key) is None and module_profile.pop(key)
        assert "numpy" in binary_profile.pop(f"{key}_reason")
    # Blender 3.4's Principled BSDF has no thin film: its material facts lack those inputs alone.
    for material in module_profile["materials"]:
        for name in ("thin_film_thickness", "thin_film_ior"):
            material["appearance"]["inputs"].pop(name, None)
    assert not any(name.startswith("thin_film") for material in binary_profile["materials"]
                   for name in material["appearance"]["inputs"])
    assert binary_profile == module_profile
