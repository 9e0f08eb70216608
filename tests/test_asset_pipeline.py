"""A real scene nobody here made (../shared/scenes/A.blend) through the whole asset path with no
step done by hand, each a real process: its dataset rendered by Cycles (datasets_gen), the
`surface` preset trained from its prior, baked into a glTF asset (export), the asset imported
into Blender and rendered from the test cameras by Cycles and EEVEE (datasets_gen --render-
asset), both scored against the ground truth (eval --renders) and shown beside the NeRF in the
report. The real scene's training makes it slow (`make test-slow`); the default run takes the
same commands from the tiny demo's shared surface run."""

from __future__ import annotations

import json
import shutil

import pytest
from conftest import run_python

from datasets_gen.core.options import options_from_keywords, options_to_argv
from nerf_contract.commands import render_asset_argv
from nerf_contract.run_layout import ASSET_DIR, ASSET_NAME, ASSET_RENDERS_DIR, METRICS_NAME, REPORT_DIR, REPORT_INDEX

TRAIN_STEPS = 600


def _render_asset(asset, dataset, out, engine: str, check: bool = True):
    argv = [*render_asset_argv(asset, dataset, engine), *options_to_argv(options_from_keywords(out_dir=str(out)))]
    return run_python("-m", "datasets_gen", *argv, check=check)


@pytest.fixture(scope="module")
def a_blend_dataset(shared_scenes, tmp_path_factory):
    out = tmp_path_factory.mktemp("a_blend") / "dataset"
    run_python("-m", "datasets_gen", str(shared_scenes / "A.blend"), "--out", str(out), "--resolution", "48",
               "--train-views", "40", "--val-views", "2", "--test-views", "3", "--samples", "16", "--seed", "0",
               "--no-progress")
    return out


def _asset_scored_in_blenders_renders(run, dataset, triangles: int, texture_size: int, test_views: int):
    """eval, export, the asset rendered by Cycles and EEVEE from the test cameras, each scored
    and the report written: the NeRF's PSNR and each engine's."""
    run_python("-m", "nerf_backend", "eval", str(run), "--no-progress")
    asset = run / ASSET_DIR / ASSET_NAME
    run_python("-m", "nerf_backend", "export", str(run), "--out", str(asset), "--triangles", str(triangles),
               "--texture-size", str(texture_size), "--no-progress")
    scores = {}
    for engine in ("cycles", "eevee"):
        renders = run / ASSET_DIR / ASSET_RENDERS_DIR / engine
        _render_asset(asset, dataset, renders, engine)
        assert sorted(p.name for p in renders.glob("r_*.png")) == [f"r_{i}.png" for i in range(test_views)]
        run_python("-m", "nerf_backend", "eval", "--dataset", str(dataset), "--renders", str(renders))
        scores[engine] = json.loads((renders / METRICS_NAME).read_text())["psnr"]
    run_python("-m", "nerf_backend", "report", str(run))
    page = (run / REPORT_DIR / REPORT_INDEX).read_text()
    assert "The baked asset in Blender&#x27;s renders" in page or "The baked asset in Blender's renders" in page
    assert f"{scores['cycles']:.2f}" in page and "the asset, CYCLES" in page and "the asset, BLENDER_EEVEE" in page
    return json.loads((run / METRICS_NAME).read_text())["psnr"], scores


def test_the_demos_surface_run_goes_to_a_scored_asset_in_blenders_renders(trained_surface_run, tiny_demo_dataset,
                                                                          tmp_path):
    """The default run's twin of the real scene's test below: the same commands on the shared
    surface run of the tiny demo (40×40, 4 test views)."""
    run = tmp_path / "run"
    shutil.copytree(trained_surface_run, run)
    nerf, scores = _asset_scored_in_blenders_renders(run, tiny_demo_dataset, 2000, 128, 4)
    print(f"the tiny demo, surface 400 steps: NeRF {nerf:.2f} dB, "
          f"asset by Cycles {scores['cycles']:.2f} dB, by EEVEE {scores['eevee']:.2f} dB")
    # Measured: NeRF 30.34 dB, the asset (2000 triangles, 128² texture) 30.80 by Cycles and
    # 30.30 by EEVEE. The same relations as the real scene's, with the demo's own floor.
    assert scores["cycles"] > nerf - 2.0 and scores["cycles"] > 28.0
    assert abs(scores["eevee"] - scores["cycles"]) < 1.0


@pytest.mark.slow
def test_a_real_scene_goes_from_training_to_a_scored_asset_in_blenders_renders(a_blend_dataset, tmp_path):
    """Slow (48 s of 2 cores' time under the default run's load): the claim on a real scene; the
    twin above runs the same commands in the default run."""
    run = tmp_path / "run"
    run_python("-m", "nerf_backend", "train", str(a_blend_dataset), "--preset", "surface", "--iters", str(TRAIN_STEPS),
               "--out", str(run), "--no-progress")
    nerf, scores = _asset_scored_in_blenders_renders(run, a_blend_dataset, 8000, 512, 3)
    print(f"A.blend at 48×48, surface {TRAIN_STEPS} steps: NeRF {nerf:.2f} dB, "
          f"asset by Cycles {scores['cycles']:.2f} dB, by EEVEE {scores['eevee']:.2f} dB")
    # Measured (band, NeuS, the bake rendering each texel as the cameras saw it): NeRF 34.86
    # dB, the asset (8000 triangles, 512² texture) 33.69 by Cycles and 33.26 by EEVEE. Baked
    # from the field's colour at the surface point instead, it was 31.80 (Cycles): 3.1 dB under.
    assert scores["cycles"] > nerf - 2.0 and scores["cycles"] > 30.0
    assert abs(scores["eevee"] - scores["cycles"]) < 1.0


def test_rendering_an_asset_refuses_bad_input_in_one_line(tiny_demo_dataset, tmp_path):
    missing = _render_asset(tmp_path / "none.glb", tiny_demo_dataset, tmp_path / "out", "cycles", check=False)
    assert missing.returncode == 2 and "none.glb: no such asset" in missing.stderr
    asset = tmp_path / "a.glb"
    asset.write_bytes(b"not a glTF file")
    no_dataset = _render_asset(asset, tmp_path / "nowhere", tmp_path / "out", "cycles", check=False)
    assert no_dataset.returncode == 2 and "transforms_test.json: not found" in no_dataset.stderr
    broken = _render_asset(asset, tiny_demo_dataset, tmp_path / "out", "eevee", check=False)
    assert broken.returncode == 2 and "a.glb: Blender's glTF importer refused it" in broken.stderr
    lone = run_python("-m", "datasets_gen", "--dataset", str(tiny_demo_dataset), "--out", str(tmp_path / "x"),
                      check=False)
    assert lone.returncode == 2 and "--dataset needs --render-asset" in lone.stderr
