"""The add-on's plain side (``addon/core``) that the Blender side hands its decisions to: the
panel's wording (wrapped text, the progress bar's shorter forms, the live view's rate, the
asset's warning), the CPU threads a job gets, when a dataset is complete, when a run can be
served, and F12's render size and empty images. Every ``addon.core`` module imports in a
Python where Blender's modules cannot."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO_ROOT

from addon.core import panel_text
from addon.core.composite_pixels import EMPTY_DEPTH, compositor_pixels, empty_pixels, render_size
from addon.core.jobs import JobStatus, dataset_complete, training_cpu_threads
from addon.core.live_view import LiveFrame, cannot_serve


def test_every_core_module_imports_where_blenders_modules_cannot():
    modules = sorted(f"addon.core.{path.stem}" for path in (REPO_ROOT / "addon" / "core").glob("*.py"))
    assert "addon.core.jobs" in modules and "addon.core.panel_text" in modules
    blocked = ("bpy", "blf", "gpu", "gpu_extras", "mathutils", "bpy_extras", "bmesh")
    script = (f"import importlib, sys\nfor name in {blocked!r}:\n    sys.modules[name] = None\n"
              f"for module in {modules!r}:\n    importlib.import_module(module)\n"
              "print(sorted(name for name in sys.modules if name.startswith('addon.blender')))\n")
    result = subprocess.run([sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip() == "[]"


# --- panel_text: one pixel a character stands in for Blender's UI font ------------------------

def test_wrap_breaks_after_spaces_and_slashes_within_the_room():
    assert panel_text.wrap("the run folder is /home/ana/renders/lego_run", 20, len) == [
        "the run folder is /", "home/ana/renders/", "lego_run"]
    assert all(len(line) <= 20 for line in panel_text.wrap("a b c " * 20, 20, len))


def test_wrap_keeps_paragraphs_and_a_word_wider_than_the_room():
    assert panel_text.wrap("first line\n\nsecond", 40, len) == ["first line", "", "second"]
    assert panel_text.wrap("tiny averyveryverylongword end", 8, len) == ["tiny", "averyveryverylongword", "end"]
    assert panel_text.wrap("", 10, len) == [""]


def test_first_fitting_takes_the_longest_that_fits_else_the_shortest():
    candidates = ["iteration 1200 of 3000, 40 s left", "Iteration 1200, 27.4 dB, 40 s left", "1200, 27.4 dB, 40 s", "1200"]
    assert panel_text.first_fitting(candidates, 40, len) == "iteration 1200 of 3000, 40 s left"
    assert panel_text.first_fitting(candidates, 20, len) == "1200, 27.4 dB, 40 s"
    assert panel_text.first_fitting(candidates, 2, len) == "1200"


def test_last_lines_keeps_the_end_after_an_ellipsis():
    lines = [f"line {n}" for n in range(10)]
    assert panel_text.last_lines(lines, 4) == ["…", "line 7", "line 8", "line 9"]
    assert panel_text.last_lines(lines[:4], 4) == lines[:4]


def test_progress_texts_of_training_shorten_for_a_narrow_sidebar():
    state = JobStatus("running", 0.4, "iteration 1200 of 3000, PSNR 27.43 dB (validation)", 40.4, 27.43, 1200)
    assert panel_text.progress_texts(state.detail, state.seconds_left, state.iteration, state.psnr) == [
        "iteration 1200 of 3000, PSNR 27.43 dB (validation), 40 s left",
        "Iteration 1200, 27.4 dB, 40 s left",
        "1200, 27.4 dB, 40 s",
        "1200"]
    # Before the first estimate and the first PSNR: only what is known.
    assert panel_text.progress_texts("iteration 3", None, 3, None) == ["iteration 3", "Iteration 3", "3", "3"]


def test_progress_texts_of_other_jobs_is_their_detail():
    assert panel_text.progress_texts("12 of 24 views rendered", None, None, None) == ["12 of 24 views rendered"]
    assert panel_text.progress_texts("Export: 1 of 4 stages", 95.0, None, None) == ["Export: 1 of 4 stages, 95 s left"]


def test_live_view_rate_counts_the_last_two_seconds():
    now = 100.0
    delivered = [(now - age, 200, 150) for age in (3.0, 2.5, 1.9, 1.2, 0.6, 0.1)]  # 4 within 2 s
    assert panel_text.live_view_rate(delivered, [0.21, 0.134], 3000, now) == "2.0 frames/s, 0.13 s each, iteration 3000"
    assert panel_text.live_view_rate(delivered[-1:], [0.5], None, now) == "Drawn, 0.50 s each"
    assert panel_text.live_view_rate([], [], None, now) == "Drawn"


def test_the_asset_warning_names_a_view_transform_other_than_standard():
    assert panel_text.asset_view_warning("Standard") == ""
    warning = panel_text.asset_view_warning("AgX")
    assert "'AgX'" in warning and warning.endswith("to see them as the NeRF does.")


# --- jobs and live_view: the decisions the buttons take ---------------------------------------

@pytest.mark.parametrize("cores, threads", [(16, 15), (2, 1), (1, 1), (None, 1)])
def test_a_job_gets_every_core_but_one(monkeypatch, cores, threads):
    monkeypatch.setattr("os.cpu_count", lambda: cores)
    assert training_cpu_threads() == threads


def test_a_dataset_is_complete_once_every_split_has_its_json(tmp_path):
    assert not dataset_complete(tmp_path / "missing")
    for split in ("train", "val"):
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps({"frames": []}))
    assert not dataset_complete(tmp_path)
    (tmp_path / "transforms_test.json").write_text(json.dumps({"frames": []}))
    assert dataset_complete(tmp_path)


def test_a_run_is_served_with_a_backend_and_a_checkpoint(tmp_path):
    assert cannot_serve("", tmp_path).startswith("no backend Python: press Set Up Backend")
    assert cannot_serve("/usr/bin/python3", tmp_path) == (
        f"{tmp_path}: no checkpoint yet: train first (a run still training is served from its first checkpoint)")
    (tmp_path / "checkpoint.pt").write_bytes(b"")
    assert cannot_serve("/usr/bin/python3", tmp_path) == ""


# --- composite_pixels: F12's images ------------------------------------------------------------

def test_the_render_size_is_the_resolution_at_its_percentage_rounded_down():
    assert render_size(1920, 1080, 100) == (1920, 1080)
    assert render_size(1920, 1080, 50) == (960, 540)
    assert render_size(101, 99, 50) == (50, 49)
    assert render_size(3, 3, 10) == (1, 1)  # never empty


def test_empty_images_are_what_a_frame_without_the_nerf_composites_to():
    colour, depth = empty_pixels(3, 2)
    assert colour.dtype == depth.dtype == np.float32 and colour.shape == depth.shape == (24,)
    assert not colour.any()
    assert (depth.reshape(-1, 4)[:, :3] == np.float32(EMPTY_DEPTH)).all() and (depth.reshape(-1, 4)[:, 3] == 1).all()
    nothing = LiveFrame(1, 3, 2, np.zeros(24, np.float32).tobytes(), np.full(6, np.inf, np.float32).tobytes(), 0.1, 0)
    frame_colour, frame_depth = compositor_pixels(nothing)
    np.testing.assert_array_equal(colour, frame_colour)
    np.testing.assert_array_equal(depth, frame_depth)
