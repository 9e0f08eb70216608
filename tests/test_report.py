"""Depth error, scoring other tools' renders, and the HTML report loaded in a real headless
Chromium: nothing broken, nothing fetched from a network, a page that is not blank."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from browser import chromium_binary, load_page
from conftest import camera_path_through_test_views, run_python
from nerf_backend.evaluation.evaluate import depth_error
from nerf_backend.core.files import write_exr


def test_depth_error_on_pixels_foreground_in_both(tmp_path):
    truth_z = np.array([[2.0, 3.0], [4.0, 0.0]], np.float32)
    truth_a = np.array([[1.0, 1.0], [1.0, 0.0]], np.float32)
    # Rendered: expected distance Σw·t is scaled by opacity; pixel (1,0) is background in the render.
    render_z = np.array([[2.1 * 0.8, 2.5], [1.0, 5.0]], np.float32)
    render_a = np.array([[0.8, 1.0], [0.2, 1.0]], np.float32)
    write_exr(tmp_path / "truth.exr", {"Z": truth_z, "A": truth_a})
    write_exr(tmp_path / "render.exr", {"Z": render_z, "A": render_a})
    error, pixels = depth_error(tmp_path / "truth.exr", tmp_path / "render.exr")
    assert pixels == 2  # (0,0) and (0,1); (1,0) is background in the render, (1,1) in the truth
    assert error == pytest.approx((abs(2.1 - 2.0) + abs(2.5 - 3.0)) / 2, abs=1e-6)
    # The render's own arrays (eval's view just rendered) score exactly as the file they were written to.
    (tmp_path / "render.exr").unlink()
    assert depth_error(tmp_path / "truth.exr", tmp_path / "render.exr", (render_z, render_a)) == (error, pixels)


def test_eval_scores_another_tools_renders(trained_run, tiny_demo_dataset, tmp_path):
    (trained_run / "renders" / "test" / "renders.json").unlink(missing_ok=True)  # rendered (and scored) afresh
    run_python("-m", "nerf_backend", "eval", str(trained_run), "--no-progress")
    run_metrics = json.loads((trained_run / "metrics.json").read_text())
    other = tmp_path / "other_tool"
    other.mkdir()
    for png in (trained_run / "renders" / "test").glob("*.png"):
        shutil.copy(png, other / png.name)  # colour only: another NeRF's output has no depth EXRs
    result = run_python("-m", "nerf_backend", "eval", "--dataset", str(tiny_demo_dataset), "--renders", str(other))
    metrics = json.loads((other / "metrics.json").read_text())
    assert metrics["psnr"] == pytest.approx(run_metrics["psnr"], abs=1e-9)
    assert metrics["ssim"] == pytest.approx(run_metrics["ssim"], abs=1e-9)
    assert run_metrics["depth_mae"] is not None and 0 < run_metrics["depth_mae"] < 1.0
    assert metrics["depth_mae"] is None and "no depth" in metrics["depth_unavailable"]
    # The run's eval scored each view as it was rendered, not read back: the files it wrote, read
    # back, score the same to the last bit, depth included.
    from_files = tmp_path / "from_files"
    run_python("-m", "nerf_backend", "eval", "--dataset", str(tiny_demo_dataset), "--renders",
               str(trained_run / "renders" / "test"), "--out", str(from_files))
    read_back = json.loads((from_files / "metrics.json").read_text())
    assert read_back["per_view"] == run_metrics["per_view"]
    assert "mean PSNR" in result.stdout
    # A view missing from the folder is named.
    (other / "r_1.png").unlink()
    failed = run_python("-m", "nerf_backend", "eval", "--dataset", str(tiny_demo_dataset), "--renders", str(other),
                        check=False)
    assert failed.returncode == 2 and "r_1.png: render not found" in failed.stderr


@pytest.fixture(scope="module")
def report_page(trained_run, tmp_path_factory):
    """A report comparing the trained run with a copy of its renders scored as another tool's."""
    # The run's own dataset: under pytest-xdist the worker that trained the shared run used its
    # own copy of the demo dataset, and a report refuses results on different datasets.
    tiny_demo_dataset = Path(json.loads((trained_run / "config.json").read_text())["dataset"])
    other = tmp_path_factory.mktemp("other") / "renders"
    other.mkdir()
    # --geometry: the run's report gains its Geometry section (the soft preview NeRF needs a threshold).
    run_python("-m", "nerf_backend", "eval", str(trained_run), "--no-progress", "--geometry", "--mesh-resolution",
               "48", "--mesh-threshold", "5")
    for png in (trained_run / "renders" / "test").glob("*.png"):
        shutil.copy(png, other / png.name)
    run_python("-m", "nerf_backend", "eval", "--dataset", str(tiny_demo_dataset), "--renders", str(other))
    # An animation beside Cycles: the report gains its Animation section with the video.
    path, _, _ = camera_path_through_test_views(tiny_demo_dataset, tmp_path_factory.mktemp("path") / "test_views")
    run_python("-m", "nerf_backend", "render", str(trained_run), "--camera-path", str(path), "--cycles", "--no-progress")
    result = run_python("-m", "nerf_backend", "report", str(trained_run), str(other))
    page = trained_run / "report" / "index.html"
    assert f"report: {page}" in result.stdout
    return page


def test_report_holds_the_headline_views_and_curves(report_page, trained_run):
    text = report_page.read_text()
    metrics = json.loads((trained_run / "metrics.json").read_text())
    assert f"{metrics['psnr']:.2f} dB" in text and "unavailable" in text and "--lpips-weights" in text
    for view in metrics["per_view"]:
        assert f">{view['view']}<" in text
    assert "Runs compared" in text and "What the run decided" in text
    assert "http://" not in text and "https://" not in text
    tables = text.split('<table class="views">')[1:]
    assert len(tables) == 2  # one per result
    for table in tables:
        psnrs = [float(v) for v in re.findall(r'<tr data-psnr="([0-9.]+)"', table.split("</table>")[0])]
        assert len(psnrs) == len(metrics["per_view"]) and psnrs == sorted(psnrs)  # worst first
    images = report_page.parent / "images"
    assert (images / "r0_training.png").is_file() and (images / "error_scale.png").is_file()
    # The run measured by eval --geometry has a Geometry section; the other tool's renders have none.
    geometry = json.loads((trained_run / "geometry.json").read_text())
    assert text.count("Geometry against the scene's true surface") == 1 and (images / "r0_geometry.png").is_file()
    assert f"<td class=num>{geometry['f_score']:.3f}</td>" in text and "F-score at τ" in text
    # The animation rendered beside Cycles: its video, the frames' mean and worst scores, the plot.
    frames = json.loads((trained_run / "animation" / "test_views" / "frame_metrics.json").read_text())
    assert text.count("Animation: test views") == 1 and (images / "r0_test_views.mp4").is_file()
    assert f"<td class=num>{frames['mean']['psnr']:.2f} dB</td>" in text and (images / "r0_test_views_metrics.png").is_file()


def test_report_in_headless_chromium(report_page, tmp_path):
    if chromium_binary() is None:
        if os.environ.get("NERF_REQUIRE_BROWSER"):
            pytest.fail("Chromium is required here (NERF_REQUIRE_BROWSER) but not installed")
        pytest.skip("no Chromium on this machine (Debian: apt-get install chromium)")
    shot = tmp_path / "report.png"
    state = load_page(report_page, shot)
    assert state["total"] > 10 and state["broken"] == []
    assert int(state["loaded"]) == state["total"]  # the page's own count, after its load event
    # Nothing from a network: the page's own files, and the browser's inline icons of the video controls.
    assert state["requests"] and all(url.startswith(("file://", "data:")) for url in state["requests"]), state["requests"]
    # The animation's H.264 video decodes: metadata read, 4 frames at 12 fps, three 40-pixel views wide.
    (video,) = state["videos"]
    assert video["error"] is None and video["ready"] >= 1 and video["width"] == 120, video
    assert video["duration"] == pytest.approx(4 / 12, abs=0.01), video
    with Image.open(shot) as image:
        pixels = np.asarray(image.convert("RGB"), dtype=np.float32)
    assert pixels.shape[0] > 1000 and pixels.shape[1] >= 1200
    assert pixels.std() > 20  # not a blank page
    assert (pixels.mean(axis=-1) < 200).mean() > 0.02  # text, pictures and plots, not white


def test_report_refuses_to_empty_a_foreign_folder(trained_run, tmp_path):
    target = tmp_path / "mine"
    target.mkdir()
    (target / "notes.txt").write_text("keep me")
    result = run_python("-m", "nerf_backend", "report", str(trained_run), "--out", str(target), check=False)
    assert result.returncode == 2 and "not a report written by this tool" in result.stderr
    assert (target / "notes.txt").read_text() == "keep me"
