"""The live view in the real Blender programs (Debian's 4.3.2 and 5.2.2 under Xvfb, software
OpenGL): a run trained on a real scene nobody here made (../shared/scenes/A.blend, rendered by
Cycles at 64×64) drawn over the 3D View by the add-on's overlay, checked pixel by pixel against
the frame the server sent: the NeRF's colour where the NeRF is, a red cube in front of it where
the cube stands, a green plane behind it only where the NeRF is not; in Solid and in Rendered
shading (EEVEE, Cycles). The session (tests/blender_scripts/live_view_session.py) orbits the view
through Blender's events, presses F12 without and with NeRF in Renders, kills the server,
disables the add-on, reloads the file and quits, and this test looks for what each left behind.

Run by ``make test-gui``; screenshots in ``out/gui-screenshots/SUITE-live-view/``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

import blender_gui
from conftest import REPO_ROOT, run_python
from test_gui import ARTIFACTS, chroot_or_skip, keep_artifacts

pytestmark = pytest.mark.gui

SHOTS_WITH_THE_NERF = ("live_1_solid", "live_2_solid_orbited", "live_3_rendered_eevee", "live_3_rendered_cycles")
FRONT, BEHIND = "Live view front cube", "Live view back plane"


@pytest.fixture(scope="module")
def a_blend_run(shared_scenes, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("live_view_a_blend")
    run_python("-m", "datasets_gen", str(shared_scenes / "A.blend"), "--out", str(root / "dataset"), "--resolution",
               "64", "--train-views", "40", "--val-views", "2", "--test-views", "3", "--samples", "16", "--seed", "0",
               "--no-progress")
    run_python("-m", "nerf_backend", "train", str(root / "dataset"), "--preset", "auto", "--iters", "600",
               "--out", str(root / "run"), "--no-progress")
    return root / "run"


@pytest.fixture(scope="module", params=blender_gui.SUITES)
def live(request, a_blend_run, shared_scenes, tmp_path_factory):
    suite = request.param
    chroot = chroot_or_skip(suite)
    work = tmp_path_factory.mktemp(f"live-view-{suite}")
    shutil.copytree(a_blend_run, work / "run")  # the dataset stays where it is: only the server reads it
    shutil.copy(shared_scenes / "A.blend", work / "A.blend")
    console = blender_gui.run_session(chroot, work, REPO_ROOT / "tests" / "blender_scripts" / "live_view_session.py",
                                      str(work / "run"), blend=work / "A.blend", timeout=1200)
    report_path = work / "live_view_report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    keep_artifacts(ARTIFACTS / f"{suite}-live-view", work, console, report_path.name, ("live_*.png", "f12_*.png", "zz_*.png"))
    return {"report": report, "console": console, "work": work}


def _shot(live, name: str):
    shots = live["work"] / "screenshots"
    return (live["report"]["live"][name], np.load(shots / f"{name}.viewport.npy"),
            np.load(shots / f"{name}.frame.npy") if (shots / f"{name}.frame.npy").is_file() else None)


def _rectangle_mask(shape, rectangle, shrink: float = 0.0) -> np.ndarray:
    """The pixels inside ``rectangle`` (x0, y0, x1, y1, rows bottom-up), shrunk by ``shrink`` of
    its size a side (negative: grown)."""
    x0, y0, x1, y1 = rectangle
    dx, dy = (x1 - x0) * shrink, (y1 - y0) * shrink
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]]
    return (xs >= x0 + dx) & (xs <= x1 - dx) & (ys >= y0 + dy) & (ys <= y1 - dy)


def test_the_session_runs_to_the_end_without_a_traceback(live):
    report = live["report"]
    assert report.get("finished"), report.get("error") or live["console"][-4000:]
    assert "Traceback" not in live["console"], live["console"][-6000:]


@pytest.mark.parametrize("name", SHOTS_WITH_THE_NERF)
def test_the_nerf_is_drawn_in_its_colour_and_depth_tested_against_the_scene(live, name):
    entry, screen, frame = _shot(live, name)
    assert entry["state"] == "ready" and frame is not None, entry
    assert frame.shape[:2] == screen.shape[:2], (frame.shape, screen.shape)  # the whole region, pixel for pixel
    alpha, depth = frame[..., 3], frame[..., 4]
    colour = frame[..., :3] / np.maximum(alpha, 1e-6)[..., None]
    front, visible = entry["rectangles"][FRONT], _rectangle_mask(alpha.shape, entry["visible"], shrink=0.01)
    near_front = _rectangle_mask(alpha.shape, front, shrink=-0.15) | ~visible  # under the sidebar is not compared
    # The NeRF where it is, away from the cube: its own colours (8-bit screen, sRGB both ways).
    nerf = (alpha > 0.98) & ~near_front
    assert nerf.sum() > 500, nerf.sum()
    error = np.abs(screen[nerf] - colour[nerf]).mean()
    assert error < 0.03, f"{name}: the NeRF's pixels differ from its frame by {error:.3f} on average"
    # The cube in front of the NeRF hides it: red where the cube stands over the NeRF.
    cube_over_nerf = _rectangle_mask(alpha.shape, front, shrink=0.2) & (alpha > 0.98)
    assert cube_over_nerf.sum() > 30, "the cube does not stand in front of the NeRF in this view"
    red = screen[cube_over_nerf]
    assert np.mean((red[:, 0] > red[:, 1] + 0.4) & (red[:, 0] > red[:, 2] + 0.4)) > 0.95, red.mean(axis=0)
    # The plane behind: green where the NeRF is empty, hidden where the NeRF is.
    empty = (alpha < 0.01) & ~near_front & np.isinf(depth)
    assert empty.sum() > 500
    green = screen[empty]
    assert np.mean((green[:, 1] > green[:, 0] + 0.3) & (green[:, 1] > green[:, 2] + 0.3)) > 0.95, green.mean(axis=0)
    assert np.mean(screen[nerf][:, 1] > screen[nerf][:, 0] + 0.3) < 0.5  # not the plane's green over the NeRF


def test_orbiting_draws_quarter_frames_then_the_whole_region(live):
    orbit = live["report"]["live"]["orbit"]
    assert orbit["view_changes"] and orbit["moving_frames"] >= 2, orbit
    width, height = orbit["region"]
    assert [-(-width // 4), -(-height // 4)] in [list(size) for size in orbit["moving_sizes"]], orbit
    assert orbit["rest_to_full_seconds"] < orbit["rest_to_exact_seconds"], orbit  # the draft, then exact
    print(f"live view over A.blend's run in Blender's GUI (software OpenGL, 2 cores shared with it): "
          f"{orbit['moving_fps']:.1f} frames a second while orbiting at {-(-width // 4)}×{-(-height // 4)}, "
          f"the whole {width}×{height} region {orbit['rest_to_full_seconds']:.2f} s after resting (exact "
          f"{orbit['rest_to_exact_seconds']:.2f} s); render "
          f"{orbit['render_seconds_median'] * 1e3:.0f} ms, upload {orbit['upload_seconds_median'] * 1e3:.1f} ms, "
          f"draw {orbit['draw_seconds_median'] * 1e3:.2f} ms (medians); the whole region's upload "
          f"{orbit['full_upload_seconds'] * 1e3:.1f} ms")


def test_f12_in_the_gui_composites_the_nerf_behind_the_cube(live):
    """F12 pressed twice from the viewport's view (Cycles, 120×80): without the NeRF, then with
    NeRF in Renders on. Where the red cube stands both renders agree (it hides the NeRF); the
    NeRF changes many pixels elsewhere; the render's server stopped with the render."""
    f12 = live["report"]["live"]["f12"]
    assert f12["turned_on"] == ["FINISHED"] and f12["message"].startswith("frame "), f12
    assert f12["server"] == "off", f12
    shots = live["work"] / "screenshots"
    alone, nerf = (iio.imread(shots / f"{name}.png").astype(np.float64) / 255 for name in ("f12_alone", "f12_nerf"))
    width, height = f12["size"]
    x0, y0, x1, y1 = f12["cube"]  # camera-view coordinates, 0-1 from the bottom left
    ys, xs = np.mgrid[0:height, 0:width]
    u, v = (xs + 0.5) / width, 1 - (ys + 0.5) / height
    inside = (u > x0 + 0.2 * (x1 - x0)) & (u < x1 - 0.2 * (x1 - x0)) & (v > y0 + 0.2 * (y1 - y0)) & (v < y1 - 0.2 * (y1 - y0))
    assert inside.sum() > 20, f12
    cube = alone[inside]
    assert (cube[:, 0] > 0.9).all() and (cube[:, 1] < 0.1).all(), "the cube is red in the render without the NeRF"
    np.testing.assert_allclose(nerf[inside], alone[inside], atol=2 / 255)
    changed = np.abs(nerf - alone)[..., :3].max(axis=-1) > 0.1
    print(f"F12 in the GUI: {int(changed.sum())} of {width * height} pixels show the NeRF; {f12['message']}")
    assert changed.sum() > 200 and not (changed & inside).any()


def test_a_killed_server_is_said_in_the_panel_draws_nothing_stale_and_restarts(live):
    report = live["report"]["live"]
    assert report["killed_state"].startswith("stopped:") and "killed" in report["killed_state"], report["killed_state"]
    killed_entry, killed, _ = _shot(live, "live_4_killed")
    _, _, last_frame = _shot(live, "live_3_rendered_cycles")
    assert killed_entry["state"].startswith("stopped")
    where_it_was = ((last_frame[..., 3] > 0.98) & _rectangle_mask(killed.shape[:2], killed_entry["visible"], 0.01)
                    & ~_rectangle_mask(killed.shape[:2], killed_entry["rectangles"][FRONT], -0.15))
    plane = killed[where_it_was]  # Solid shading again: the plane's flat green shows through
    assert np.mean((plane[:, 1] > plane[:, 0] + 0.3) & (plane[:, 1] > plane[:, 2] + 0.3)) > 0.95, plane.mean(axis=0)
    assert report["live_5_restarted"]["state"] == "ready"


@pytest.mark.parametrize("moment", ("disabled", "reloaded"))
def test_disabling_the_add_on_or_reloading_the_file_leaves_no_process_and_no_frames(live, moment):
    left = live["report"]["live"][moment]
    assert left["pid"] and left["folder"], left
    assert not left["process_alive"] and not left["folder_exists"], left


def test_quitting_blender_leaves_no_process_and_no_frames(live):
    left = live["report"]["live"]["at_quit"]
    assert left["pid"] and left["folder"], left
    assert not Path(f"/proc/{left['pid']}").exists() or "zombie" in Path(f"/proc/{left['pid']}/status").read_text()
    assert not Path(left["folder"]).exists(), left
