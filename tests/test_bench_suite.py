"""The benchmark suite: the built-in trap scenes are what they say, `datasets_gen --suite`
renders and resumes every dataset, `bench --suite` benches and summarises every scene.

Everything is tiny (24×24 images, 2/1/1 views, 4 Cycles samples; 5 training iterations), so
the numbers checked are the scenes' geometry and the bookkeeping, not NeRF quality."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import run_python
from PIL import Image

from datasets_gen.core.builtin_scenes import SUITE_BUILTINS, TRAP_SCENES
from nerf_backend.bench import scene_blank_psnr
from nerf_backend.data.occupancy_prior import GLASS_MIN_WALL_SHARE, load_occupancy_prior
from nerf_backend.bench.suite import SuiteDataset, scene_summary

TINY = ["--resolution", "24", "--train-views", "2", "--val-views", "1", "--test-views", "1", "--samples", "4"]
SPLITS = ("train", "val", "test")
ROBOT = "RobotExpressive"


def _files(folder: Path) -> dict[str, int]:
    """Every file under `folder` with its modification time (ns): what "kept" must not change."""
    return {str(path.relative_to(folder)): path.stat().st_mtime_ns for path in sorted(folder.rglob("*"))
            if path.is_file()}


def _with(args: list[str], flag: str, value: str) -> list[str]:
    """`args` with the value after `flag` replaced."""
    at = args.index(flag) + 1
    return args[:at] + [value] + args[at + 1:]


def _rgba(dataset: Path, split: str) -> list[np.ndarray]:
    meta = json.loads((dataset / f"transforms_{split}.json").read_text())
    return [np.asarray(Image.open(dataset / f"{frame['file_path']}.png").convert("RGBA"), dtype=np.float64) / 255
            for frame in meta["frames"]]


@pytest.fixture(scope="module")
def tiny_suite(tmp_path_factory, shared_scenes) -> Path:
    """The suite at 24×24, with RobotExpressive.blend (a missing texture: --allow-missing)."""
    out = tmp_path_factory.mktemp("suite") / "suite"
    run_python("-m", "datasets_gen", "--suite", str(out), "--suite-scene", str(shared_scenes / f"{ROBOT}.blend"),
               "--allow-missing", *TINY, "--no-progress")
    return out


def test_suite_renders_every_dataset_and_keeps_or_resumes_them(tiny_suite, shared_scenes):
    suite_args = ["-m", "datasets_gen", "--suite", str(tiny_suite), "--suite-scene",
                  str(shared_scenes / f"{ROBOT}.blend"), "--allow-missing", *TINY, "--no-progress"]
    assert sorted(p.name for p in tiny_suite.iterdir()) == sorted(SUITE_BUILTINS + (ROBOT,))
    for name in SUITE_BUILTINS + (ROBOT,):
        dataset = tiny_suite / name
        for split, count in zip(SPLITS, (2, 1, 1)):
            assert len(json.loads((dataset / f"transforms_{split}.json").read_text())["frames"]) == count
            assert all(image.shape == (24, 24, 4) for image in _rgba(dataset, split))
        settings = json.loads((dataset / "transforms_train.json").read_text())["generator"]["settings"]
        profile = json.loads((dataset / "scene_profile.json").read_text())
        assert settings["samples"] == 4 and settings["allow_missing"] is True  # the flags reach every scene
        if name == ROBOT:
            # The same file, however it was reached (../shared may be a symbolic link).
            assert Path(settings["scene"]["source"]).resolve() == (shared_scenes / f"{ROBOT}.blend").resolve()
            assert "builtin" not in profile and any(texture["missing"] for texture in profile["textures"])
        else:  # each built-in scene records its name
            assert profile["builtin"] == name
            assert settings["scene"] == ({"source": "demo", "demo_variant": "standard"} if name == "demo"
                                         else {"source": "builtin", "builtin": name})

    before = _files(tiny_suite)
    again = run_python(*suite_args)
    assert again.stderr.count("complete, kept") == len(SUITE_BUILTINS) + 1
    assert _files(tiny_suite) == before  # kept means untouched

    other = run_python(*_with(suite_args, "--samples", "8"), check=False)
    assert other.returncode == 2
    assert "samples 4 there vs 8 now" in other.stderr and "--overwrite" in other.stderr
    assert _files(tiny_suite) == before  # refused before anything rendered

    # An interrupted render (its progress file, no JSON, a view missing) is resumed, not redone.
    demo = tiny_suite / "demo"
    generator = json.loads((demo / "transforms_train.json").read_text())["generator"]
    (demo / ".datasets_gen_progress.json").write_text(json.dumps({
        "generator": "datasets_gen", "settings": generator["settings"],
        "blender_version": generator["blender_version"], "shard": None}))
    for split in SPLITS:
        (demo / f"transforms_{split}.json").unlink()
    (demo / "test" / "r_0.png").unlink()
    kept_view = (demo / "train" / "r_0.png").stat().st_mtime_ns
    resumed = run_python(*suite_args)
    assert "demo: resuming the incomplete dataset" in resumed.stderr
    assert "3 views already complete, 1 to render" in resumed.stderr
    assert (demo / "test" / "r_0.png").is_file() and (demo / "transforms_test.json").is_file()
    assert (demo / "train" / "r_0.png").stat().st_mtime_ns == kept_view


def _silhouette_centre(dataset: Path) -> np.ndarray:
    """Least-squares meeting point of the rays through each view's alpha centroid: where the
    geometry's mass is, seen from every view."""
    normal_matrix, right_side = np.zeros((3, 3)), np.zeros(3)
    for split in SPLITS:
        meta = json.loads((dataset / f"transforms_{split}.json").read_text())
        for frame, rgba in zip(meta["frames"], _rgba(dataset, split)):
            alpha = rgba[..., 3]
            rows, columns = np.mgrid[0:alpha.shape[0], 0:alpha.shape[1]] + 0.5
            u, v = (alpha * columns).sum() / alpha.sum(), (alpha * rows).sum() / alpha.sum()
            pose = np.array(frame["transform_matrix"])
            direction = pose[:3, :3] @ [(u - meta["cx"]) / meta["fl_x"], -(v - meta["cy"]) / meta["fl_y"], -1.0]
            direction /= np.linalg.norm(direction)
            projector = np.eye(3) - np.outer(direction, direction)
            normal_matrix += projector
            right_side += projector @ pose[:3, 3]
    return np.linalg.solve(normal_matrix, right_side)


def _offset_from_bounds_centre(dataset: Path) -> float:
    """Distance of the silhouette centre from the bounds' centre, in bounds half-diagonals."""
    bounds = json.loads((dataset / "scene_profile.json").read_text())["bounds"]
    low, high = np.array(bounds["min"]), np.array(bounds["max"])
    return float(np.linalg.norm(_silhouette_centre(dataset) - (low + high) / 2) / (np.linalg.norm(high - low) / 2))


def _partial_coverage(dataset: Path) -> float:
    """Of the pixels anything covers (alpha > 0.02), the fraction covered partly (alpha < 0.9):
    near 1 for structures thinner than a pixel."""
    alpha = np.concatenate([rgba[..., 3].ravel() for split in SPLITS for rgba in _rgba(dataset, split)])
    covered = alpha[alpha > 0.02]
    return float((covered < 0.9).mean())


def test_trap_scenes_are_what_they_say(tiny_suite):
    assert set(TRAP_SCENES) <= set(SUITE_BUILTINS)
    profiles = {name: json.loads((tiny_suite / name / "scene_profile.json").read_text()) for name in TRAP_SCENES}
    for profile in profiles.values():  # fitted like a user's scene
        assert profile["world_to_nerf"]["rule"].startswith("fit")

    bright = tiny_suite / "bright_object"
    test_views = _rgba(bright, "test")
    mean_alpha = float(np.mean([rgba[..., 3].mean() for rgba in test_views]))
    assert 0.45 <= mean_alpha <= 0.75, mean_alpha  # measured 0.59: a large object
    object_colour = np.concatenate([rgba[..., :3][rgba[..., 3] > 0.5] for rgba in test_views]).mean(axis=0)
    assert object_colour.min() > 0.8, object_colour  # measured 0.91 each: white

    thin, solid = _partial_coverage(tiny_suite / "thin_structure"), _partial_coverage(bright)
    assert thin > 0.7 and solid < 0.3, (thin, solid)  # measured 0.93 and 0.15

    off, centred = _offset_from_bounds_centre(tiny_suite / "off_centre"), _offset_from_bounds_centre(bright)
    assert off > 0.4 and centred < 0.05, (off, centred)  # measured 0.54 and 0.00 half-diagonals

    extent = np.subtract(profiles["ground_plane"]["bounds"]["max"], profiles["ground_plane"]["bounds"]["min"])
    assert min(extent[0], extent[1]) > 5 * extent[2], extent  # measured 7.5 times wider than tall

    glass = profiles["glass_and_gloss"]
    assert glass["transparency"] is True and glass["view_dependent"] is True
    materials = {material["name"]: material for material in glass["materials"]}
    assert materials["glass"]["transparent"] and any("transmission 1" in r for r in materials["glass"]["reasons"])
    assert any("metallic 1" in r for r in materials["chrome"]["reasons"])
    assert not materials["base"]["view_dependent"]  # the base is diffuse

    # The material traps: the surface each stands for is a region of its profile and of its
    # prior's cells, beside its diffuse base or board.
    for name, region, material in (("glass_over_checker", "transmissive", "glass"), ("mirror_in_room", "metal", "silver"),
                                   ("rough_in_room", "metal", "silver"), ("thin_film_coat", "thin_film", "soap film")):
        shares = profiles[name]["occupancy_prior"]["regions"]
        assert set(shares) == {region, "diffuse"} and shares[region] > 0.1, (name, shares)
        found = {m["name"]: m for m in profiles[name]["materials"]}[material]
        assert found["region"] == region and found["view_dependent"], (name, found)
    # The hollow glass: one body of smooth glass whose walls are thin for its size (its mean chord
    # under a tenth of its diagonal), which the plan leaves to the field with straight rays.
    dish = load_occupancy_prior(tiny_suite / "glass_dish", "solid")
    assert dish.glass_surfaces() is None and list(dish.glass_materials) == list(dish.thin_glass())
    assert [len(shares) for shares in dish.thin_glass().values()] == [1], dish.thin_glass()
    assert max(dish.thin_glass().values())[0] < 0.5 * GLASS_MIN_WALL_SHARE, dish.thin_glass()
    roughness = {name: {m["name"]: m for m in profiles[name]["materials"]}["silver"]["appearance"]["inputs"]["roughness"]["value"]
                 for name in ("mirror_in_room", "rough_in_room")}
    # The same objects in two finishes (Blender keeps the values in single precision).
    assert roughness == pytest.approx({"mirror_in_room": 0.03, "rough_in_room": 0.45}, abs=1e-6), roughness


def _profile_from_check(*args: str) -> str:
    stdout = run_python("-m", "datasets_gen", *args, "--check", *TINY).stdout
    return stdout[stdout.index("\n{\n") + 1:] if "\n{\n" in stdout else stdout


def test_demo_flags_are_shorthands_for_the_demo_builtins(tmp_path):
    assert _profile_from_check("--builtin", "demo") == _profile_from_check("--demo")
    out = tmp_path / "demo_diffuse"
    run_python("-m", "datasets_gen", "--builtin", "demo_diffuse", "--out", str(out), *TINY, "--no-progress")
    profile = json.loads((out / "scene_profile.json").read_text())
    assert profile == json.loads(_profile_from_check("--demo", "--demo-variant", "diffuse"))
    assert profile["builtin"] == "demo_diffuse" and profile["view_dependent"] is False
    settings = json.loads((out / "transforms_train.json").read_text())["generator"]["settings"]
    assert settings["scene"] == {"source": "demo", "demo_variant": "diffuse"} and settings["frame"] == "blender"
    refused = run_python("-m", "datasets_gen", "--builtin", "demo", "--demo", "--out", str(tmp_path / "x"),
                         check=False)
    assert refused.returncode == 2 and "exactly one of SCENE.blend, --demo or --builtin" in refused.stderr


def _direct_blank_psnr(dataset: Path) -> float:
    """The all-white image against each test view composited on white, from the PNGs."""
    values = []
    for rgba in _rgba(dataset, "test"):
        on_white = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
        values.append(-10.0 * np.log10(np.mean((1.0 - on_white) ** 2)))
    return float(np.mean(values))


SUMMARY_COLUMNS = {"variant", "preset", "psnr", "ssim", "time_to_25_db_s", "time_to_30_db_s", "seconds_per_iteration",
                   "iterations", "rays_per_second", "samples_per_second", "blank_psnr", "collapse_detected",
                   "collapse_events", "collapsed"}


def test_bench_suite_benches_every_scene_resumes_and_refuses_to_overwrite(tiny_suite, tmp_path):
    bench = tmp_path / "bench"
    common = ["--presets", "fast,auto", "--iters", "5", "--points", "1", "--curve-views", "1", "--out", str(bench)]
    first, second = tiny_suite / "bright_object", tiny_suite / "off_centre"
    run_python("-m", "nerf_backend", "bench", "--suite", str(first), *common)
    finished = (bench / "bright_object" / "bench.json").stat().st_mtime_ns
    (bench / "off_centre" / "runs" / "fast").mkdir(parents=True)  # an interrupted bench of the second scene
    (bench / "off_centre" / "runs" / "fast" / "events.jsonl").write_text("")
    result = run_python("-m", "nerf_backend", "bench", "--suite", str(first), str(second), *common)
    assert "bright_object: finished bench kept" in result.stderr
    assert "off_centre: benching again (unfinished)" in result.stderr
    assert (bench / "bright_object" / "bench.json").stat().st_mtime_ns == finished

    for name in ("bright_object", "off_centre"):
        for output in ("bench.json", "bench.md", "bench.png"):
            assert (bench / name / output).is_file(), (name, output)
    summary = json.loads((bench / "summary.json").read_text())
    assert summary["budget"] == {"iterations": 5}
    assert [scene["scene"] for scene in summary["scenes"]] == ["bright_object", "off_centre"]
    for scene, dataset in zip(summary["scenes"], (first, second)):
        assert scene["blank_psnr"] == pytest.approx(_direct_blank_psnr(dataset), abs=1e-4)
        assert scene["blank_views"] == 1 and scene["empty_test_views"] == 0
        rows = {row["variant"]: row for row in scene["variants"]}
        assert set(rows) == {"fast", "auto"}
        for row in rows.values():
            assert set(row) == SUMMARY_COLUMNS
            assert row["iterations"] == 5 and 0 < row["seconds_per_iteration"] < 60
            assert row["rays_per_second"] > 0 and row["samples_per_second"] > 0
            assert 5 < row["psnr"] < 60 and 0 < row["ssim"] <= 1 and row["blank_psnr"] == scene["blank_psnr"]
            assert row["collapsed"] == (row["psnr"] < scene["blank_psnr"] + 1.0)
            assert isinstance(row["collapse_detected"], bool)
        assert scene["best_fixed"] == {"variant": "fast", "psnr": rows["fast"]["psnr"]}
        assert scene["auto"]["gap_to_best_fixed_db"] == pytest.approx(rows["auto"]["psnr"] - rows["fast"]["psnr"])
    table = (bench / "summary.md").read_text()
    for column in ("test PSNR", "SSIM", "s to 25 / 30 dB", "s/iteration", "iterations", "blank PSNR",
                   "collapse detected / final", "best fixed variant", "auto − best fixed"):
        assert column in table
    assert table.count("\n| bright_object |") == 3 and table.count("\n| off_centre |") == 3  # 2 variants + gap
    with Image.open(bench / "summary.png") as plot:
        assert plot.size[0] > 400 and plot.size[1] > 300

    before = _files(bench)
    refused = run_python("-m", "nerf_backend", "bench", "--suite", str(first), str(second),
                         *_with(common, "--iters", "6"), check=False)
    assert refused.returncode == 2
    assert "budget 5 iterations there vs 6 iterations now" in refused.stderr and "--overwrite" in refused.stderr
    assert _files(bench) == before


def test_collapse_detected_from_the_trainers_events_and_judged_from_the_blank_image(tiny_suite, tmp_path):
    dataset = tiny_suite / "bright_object"
    blank = scene_blank_psnr(dataset)["psnr"]
    assert blank == pytest.approx(_direct_blank_psnr(dataset), abs=1e-4)
    event = {"event": "collapse", "iteration": 250, "val_psnr": blank + 0.3, "blank_psnr": blank, "margin_db": 1.0,
             "action": "restarted: ...", "reason": "validation PSNR within 1 dB of the blank image's"}
    (tmp_path / "runs" / "auto").mkdir(parents=True)
    (tmp_path / "runs" / "auto" / "events.jsonl").write_text(
        json.dumps({"event": "val", "iteration": 250, "psnr": blank + 0.3}) + "\n" + json.dumps(event) + "\n")

    def variant(name: str, psnr: float) -> dict:
        return {"name": name, "preset": name, "time_to_psnr_s": {"20": 1.0, "25": None, "30": None},
                "final": {"psnr": psnr, "ssim": 0.5, "iterations": 100, "train_seconds": 20.0}}

    bench = {"variants": [variant("fast", blank + 0.5), variant("preview", blank + 2.0), variant("auto", blank + 6.0)]}
    scene = scene_summary(SuiteDataset("bright_object", dataset), bench, tmp_path)
    rows = {row["variant"]: row for row in scene["variants"]}
    assert (rows["fast"]["collapsed"], rows["preview"]["collapsed"], rows["auto"]["collapsed"]) == (True, False, False)
    assert not rows["fast"]["collapse_detected"] and rows["auto"]["collapse_detected"]  # recovered after it
    assert rows["auto"]["collapse_events"][0]["iteration"] == 250
    assert rows["auto"]["collapse_events"][0]["action"] == "restarted: ..."
    assert rows["fast"]["seconds_per_iteration"] == pytest.approx(0.2)
    assert scene["best_fixed"]["variant"] == "preview"
    assert scene["auto"]["gap_to_best_fixed_db"] == pytest.approx(4.0)
    assert os.path.samefile(scene["dataset"], dataset)
