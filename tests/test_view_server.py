"""``serve RUN``: the live view's render server as the add-on runs it, a real subprocess talking
through its pipes and frame files (nerf_contract.view_frames). Its frames against the run's own
renderer, depth against the camera, latest request wins, and every way it can end."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from nerf_backend.core.cameras import (Intrinsics, camera_rays, pixel_centres, pixels_seeing_boxes,
                                       ray_box_intersection, rays_from_matrices)
from nerf_backend.data.dataset import load_split
from nerf_backend.data.run_folder import RunFolder
from nerf_backend.evaluation.inference import load_trained_model
from nerf_backend.evaluation.render_views import render_image
from nerf_backend.evaluation.view_server import Frame, FrameWriter, LiveModel
from nerf_contract import commands, view_frames

from conftest import REPO_ROOT, run_python

NEAR, FAR = 0.05, 100.0


def perspective(intrinsics, width: int, height: int) -> list[list[float]]:
    """OpenGL's projection of pinhole intrinsics scaled to ``width × height`` (Blender's
    window_matrix for that camera)."""
    sx, sy = width / intrinsics.width, height / intrinsics.height
    fx, fy, cx, cy = intrinsics.fl_x * sx, intrinsics.fl_y * sy, intrinsics.cx * sx, intrinsics.cy * sy
    return [[2 * fx / width, 0.0, 1 - 2 * cx / width, 0.0], [0.0, 2 * fy / height, 2 * cy / height - 1, 0.0],
            [0.0, 0.0, -(FAR + NEAR) / (FAR - NEAR), -2 * FAR * NEAR / (FAR - NEAR)], [0.0, 0.0, -1.0, 0.0]]


def orthographic(half_width: float, half_height: float) -> list[list[float]]:
    return [[1 / half_width, 0.0, 0.0, 0.0], [0.0, 1 / half_height, 0.0, 0.0],
            [0.0, 0.0, -2 / (FAR - NEAR), -(FAR + NEAR) / (FAR - NEAR)], [0.0, 0.0, 0.0, 1.0]]


class Server:
    """``python -m nerf_backend serve`` as the add-on starts it, with its pipes."""

    def __init__(self, run: Path, frames: Path, *extra: str):
        frames.mkdir(parents=True, exist_ok=True)
        argv = commands.serve_argv(str(run), str(frames), device="cpu")
        self.process = subprocess.Popen(commands.backend_command(sys.executable, [*argv, *extra]), cwd=REPO_ROOT,
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                        text=True)
        self.ready = self.event()

    def send(self, line: str) -> None:
        self.process.stdin.write(line + "\n")
        self.process.stdin.flush()

    def event(self) -> dict:
        line = self.process.stdout.readline()
        event = view_frames.parse_event(line)
        assert event is not None, f"not an event: {line!r}; stderr: {self.process.stderr.read()[-2000:]}"
        return event

    def frame(self, event: dict) -> tuple[np.ndarray, np.ndarray]:
        """RGBA and depth of a ``frame`` event, rows top to bottom."""
        frames = view_frames.FrameFile.open(event["file"])
        try:
            width, height, rgba, depth = frames.read(event["slot"], event["sequence"])
        finally:
            frames.close()
        return (np.frombuffer(rgba, np.float32).reshape(height, width, 4)[::-1],
                np.frombuffer(depth, np.float32).reshape(height, width)[::-1])

    def finish(self, timeout: float = 60) -> str:
        """What the server writes until it exits (by its own choice: its stdin stays open)."""
        self.process.wait(timeout)  # its few last lines fit the pipe's buffer
        return self.process.stdout.read()


@pytest.fixture(scope="module")
def test_view(trained_run):
    split = load_split(RunFolder(trained_run).read_config()["dataset"], "test")
    return split.intrinsics, split.poses[0]


def _request(request_id, intrinsics, pose, width, height, **extra) -> str:
    view = torch.linalg.inv(pose.double()).tolist()
    return view_frames.render_request(request_id, view_matrix=view, projection_matrix=perspective(intrinsics, width,
                                                                                                  height),
                                      width=width, height=height, **extra)


def test_rays_of_a_projection_are_the_pinhole_cameras(test_view):
    """The rays unprojected from OpenGL matrices are the pinhole rays of the same camera."""
    intrinsics, pose = test_view
    width, height = 31, 17  # odd and unequal: a transposed or flipped axis shows
    scaled = intrinsics.scaled(1.0)
    origins, directions = rays_from_matrices(torch.linalg.inv(pose.double()).float(),
                                             torch.tensor(perspective(scaled, width, height)), width, height)
    k = Intrinsics(width, height, scaled.fl_x * width / scaled.width, scaled.fl_y * height / scaled.height,
                   scaled.cx * width / scaled.width, scaled.cy * height / scaled.height)
    pinhole_origins, pinhole_directions = camera_rays(k, pose, pixel_centres(width, torch.arange(width * height)))
    assert torch.allclose(directions, pinhole_directions, atol=2e-6)
    # Origins sit on the near plane: the camera's centre plus NEAR / cos(angle) along the ray.
    cosine = -(pinhole_directions @ pose[:3, 2])
    assert torch.allclose(origins, pinhole_origins + (NEAR / cosine)[:, None] * pinhole_directions, atol=1e-5)


def test_an_orthographic_views_rays_are_parallel(test_view):
    _, pose = test_view
    origins, directions = rays_from_matrices(torch.linalg.inv(pose.double()).float(),
                                             torch.tensor(orthographic(2.0, 1.0)), 8, 4)
    assert torch.allclose(directions, -pose[:3, 2].expand(32, 3), atol=1e-6)
    spread = (origins - origins.mean(dim=0)) @ pose[:3, :3]  # in the camera's axes
    assert spread[:, 0].abs().max() == pytest.approx(2.0 * 7 / 8, abs=1e-5)
    assert spread[:, 1].abs().max() == pytest.approx(1.0 * 3 / 4, abs=1e-5)


def _boxes_hit(origins, directions, corners):
    """Whether each ray meets one of the boxes (the project's slab test, box by box)."""
    hit = torch.zeros(origins.shape[0], dtype=torch.bool)
    for box in corners:
        hit |= ray_box_intersection(origins, directions, box.amin(dim=0), box.amax(dim=0))[2]
    return hit


@pytest.mark.parametrize("kind", ["perspective", "orthographic"])
def test_the_pixels_left_out_see_none_of_the_boxes(kind):
    """``pixels_seeing_boxes`` keeps every pixel whose ray meets a box (checked by a slab test
    of every pixel's ray, 40 random views of 12 random boxes) and leaves most of the rest out;
    with a box behind a perspective camera it keeps every pixel (None)."""
    generator = torch.Generator().manual_seed(3)
    width, height = 37, 23
    kept_share = []
    for _ in range(40):
        low = torch.rand(12, 3, generator=generator) * 2 - 1
        high = low + torch.rand(12, 3, generator=generator) * 0.3
        corners = torch.stack([torch.where(torch.tensor([(c >> a) & 1 for a in range(3)]).bool(), high, low)
                               for c in range(8)], dim=1)
        eye = torch.nn.functional.normalize(torch.randn(3, generator=generator), dim=0) * 4
        pose = torch.eye(4, dtype=torch.float64)
        back = torch.nn.functional.normalize(eye.double(), dim=0)
        right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                                                                 back), dim=0)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, torch.linalg.cross(back, right), back, eye
        view = torch.linalg.inv(pose)
        projection = torch.tensor(orthographic(1.5, 1.0) if kind == "orthographic" else
                                  perspective(Intrinsics(width, height, 30.0, 30.0, 18.0, 12.0), width, height))
        origins, directions = rays_from_matrices(view, projection, width, height)
        hit = _boxes_hit(origins, directions, corners).nonzero().squeeze(1)
        seen = pixels_seeing_boxes(corners, view, projection, width, height)
        assert hit.numel() > 0 and set(hit.tolist()) <= set(seen.tolist())
        kept_share.append((seen.numel() - hit.numel()) / (width * height - hit.numel()))
    assert np.mean(kept_share) < 0.5, kept_share  # the rectangles and their margin keep some empty pixels
    behind = corners + torch.tensor(eye.tolist()) * 2  # the boxes moved past the camera
    # A perspective projection wraps round behind the camera; an orthographic one does not.
    assert (pixels_seeing_boxes(behind, view, projection, width, height) is None) == (kind == "perspective")


@pytest.mark.parametrize("run_fixture", ["trained_run", "trained_marched_run"])
def test_frames_match_the_runs_renderer_with_the_cameras_depth(run_fixture, test_view, tmp_path, request):
    """A served frame is the run's own render of that camera (colour within 1e-3 once composited
    over white), its alpha the opacity, its depth the camera's z of the expected surface. The
    marched model's frame renders only the pixels that see its occupied blocks: the others
    must be as empty as the whole render has them."""
    trained_run = request.getfixturevalue(run_fixture)
    intrinsics, pose = test_view
    width, height = intrinsics.width, intrinsics.height
    server = Server(trained_run, tmp_path / "frames")
    assert server.ready["event"] == view_frames.READY
    server.send(_request(7, intrinsics, pose, width, height))
    event = server.event()
    assert (event["event"], event["id"], event["width"], event["height"]) == ("frame", 7, width, height)
    rgba, depth = server.frame(event)
    server.send(view_frames.quit_request())
    assert '"reason": "asked to quit"' in server.finish()

    model, ray_bounds, _ = load_trained_model(RunFolder(trained_run), torch.device("cpu"))
    reference = render_image(model, intrinsics, pose, ray_bounds)
    over_white = rgba[..., :3] + (1 - rgba[..., 3:])
    assert np.abs(over_white - reference.rgb).max() < 1e-3
    assert np.abs(rgba[..., 3] - reference.opacity).max() < 1e-3
    hit = reference.opacity > 0.5
    assert hit.mean() > 0.05, "the test view should show the demo's objects"
    pixels = torch.arange(width * height)
    _, directions = camera_rays(intrinsics, pose, pixel_centres(width, pixels))
    cosine = (-(directions @ pose[:3, 2])).reshape(height, width).numpy()
    expected = reference.depth / np.maximum(reference.opacity, 1e-4) * cosine
    assert np.allclose(depth[hit], expected[hit], rtol=1e-3, atol=1e-3)
    assert np.isinf(depth[reference.opacity < 1e-5]).all()
    assert not any(tmp_path.joinpath("frames").iterdir()), "the server leaves no frame file behind"
    if run_fixture == "trained_marched_run":  # the view leaves pixels out, so the check above meant something
        live = LiveModel(RunFolder(trained_run), torch.device("cpu"))
        seen = pixels_seeing_boxes(live.model.content_corners(), torch.linalg.inv(pose.double()) @ live.nerf_to_world,
                                   torch.tensor(perspective(intrinsics, width, height)), width, height)
        assert 0 < seen.numel() < 0.9 * width * height


def test_a_draft_marches_a_coarser_step_close_to_the_exact_frame(trained_marched_run, tmp_path):
    """``step_scale`` 2 (the add-on's drafts): fewer samples a ray, so not the exact frame, yet
    within 30 dB of it where the model is (opacity and depth too); the model's own step is
    back afterwards (the next exact frame is the first one, bit for bit)."""
    split = load_split(RunFolder(trained_marched_run).read_config()["dataset"], "test")
    intrinsics, pose = split.intrinsics, split.poses[0]
    server = Server(trained_marched_run, tmp_path / "frames")
    frames = {}
    for request_id, scale in ((1, 1.0), (2, view_frames.DRAFT_STEP_SCALE), (3, 1.0)):
        server.send(_request(request_id, intrinsics, pose, 40, 40, step_scale=scale))
        frames[request_id] = server.frame(server.event())
    server.send(view_frames.quit_request())
    (exact, exact_depth), (draft, draft_depth), (again, _) = frames[1], frames[2], frames[3]
    assert np.array_equal(exact, again)
    difference = np.abs(draft - exact)
    psnr = 10 * np.log10(1.0 / float(np.mean(difference[..., :3] ** 2)))
    print(f"draft (step ×{view_frames.DRAFT_STEP_SCALE:g}) against exact, 40×40: {psnr:.2f} dB, "
          f"opacity off by {float(difference[..., 3].max()):.4f} at most")
    assert difference.max() > 0 and psnr > 30.0  # measured 37.3 dB
    hit = np.isfinite(exact_depth) & np.isfinite(draft_depth) & (exact[..., 3] > 0.99)
    assert hit.sum() > 100 and np.median(np.abs(draft_depth[hit] - exact_depth[hit]) / exact_depth[hit]) < 0.01


def test_the_latest_request_wins_and_bad_ones_get_one_line(trained_run, test_view, tmp_path):
    intrinsics, pose = test_view
    server = Server(trained_run, tmp_path / "frames")
    server.send("not json")
    assert server.event() == {"event": "error", "id": None, "message": "not a request: not json"}
    bad = view_frames.render_request(1, view_matrix=[[1.0, 0.0], [0.0, 1.0]], projection_matrix=view_frames.IDENTITY,
                                     width=8, height=8)
    server.send(bad)
    assert server.event()["message"] == "request 1: view_matrix must be a 4×4 matrix of finite numbers"
    for scale in (0.5, 9, "2", True):
        request = json.loads(_request(2, intrinsics, pose, 8, 8))
        server.send(json.dumps({**request, "step_scale": scale}))
        refused = "request 2: step_scale must be a number from 1 to 8"
        assert server.event() == {"event": "error", "id": 2, "message": refused}
    # Six requests at once: each replaces the one before it while it waits, so the server draws
    # the last, and the first only where it took it before the others arrived.
    server.process.stdin.write("".join(_request(i, intrinsics, pose, 48, 48) + "\n" for i in range(10, 16)))
    server.process.stdin.flush()
    ids = []
    while not ids or ids[-1] != 15:
        event = server.event()
        assert event["event"] == "frame", event
        ids.append(event["id"])
    assert set(ids) <= {10, 15}, ids
    server.process.stdin.close()
    assert '"reason": "its parent closed the request pipe"' in server.finish()


def test_a_frame_larger_than_its_file_goes_into_a_new_one(tmp_path):
    writer = FrameWriter(tmp_path)
    small = writer.write(Frame(np.zeros((8, 8, 4), np.float32), np.zeros((8, 8), np.float32), 0.1), 1, 5)
    large = writer.write(Frame(np.ones((300, 400, 4), np.float32), np.full((300, 400), 2.0, np.float32), 0.2), 2, 5)
    assert large["file"] != small["file"] and (large["width"], large["height"]) == (400, 300)
    assert not Path(small["file"]).exists(), "the outgrown file is removed"
    reader = view_frames.FrameFile.open(large["file"])
    width, height, rgba, depth = reader.read(large["slot"], large["sequence"])
    assert (width, height) == (400, 300)
    assert np.frombuffer(rgba, np.float32).min() == 1.0 and np.frombuffer(depth, np.float32).max() == 2.0
    reader.close()
    writer.close()
    assert not any(tmp_path.iterdir())


def test_a_stale_slot_is_refused(tmp_path):
    """A reader holding a frame event after the server wrote that slot again gets None."""
    frames = view_frames.FrameFile.create(str(tmp_path / "f.bin"), capacity=4)
    sequence = frames.begin_frame(0)
    frames.end_frame(0, sequence, 1, 2, 2, 0.1, 5)
    reader = view_frames.FrameFile.open(str(tmp_path / "f.bin"))
    assert reader.read(0, sequence)[:2] == (2, 2)
    frames.begin_frame(0)  # written again: odd while being written, then a new sequence
    assert reader.read(0, sequence) is None
    reader.close()
    frames.remove()
    (tmp_path / "junk.bin").write_bytes(b"x" * 5000)
    with pytest.raises(ValueError, match="junk.bin: not a version 1 frame file"):
        view_frames.FrameFile.open(str(tmp_path / "junk.bin"))


def test_a_training_run_reloads_and_a_deleted_run_stops_the_server(trained_run, test_view, tmp_path):
    intrinsics, pose = test_view
    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    server = Server(run, tmp_path / "frames")
    # Training replaces the checkpoint atomically (os.replace): the server loads the new one.
    checkpoint = RunFolder(run).checkpoint_path
    shutil.copy(checkpoint, tmp_path / "newer.pt")
    time.sleep(2.1)  # RELOAD_CHECK_SECONDS
    os.replace(tmp_path / "newer.pt", checkpoint)
    server.send(_request(1, intrinsics, pose, 16, 16))
    assert server.event()["event"] == "reloaded"
    assert server.event()["event"] == "frame"
    shutil.rmtree(run)
    time.sleep(2.1)
    server.send(_request(2, intrinsics, pose, 16, 16))
    out = server.finish()
    assert f"{checkpoint}: the run's checkpoint is gone (the run folder was deleted or moved)" in out
    assert server.process.returncode == 0
    assert not any(tmp_path.joinpath("frames").iterdir())


def test_an_idle_server_stops(trained_run, tmp_path):
    server = Server(trained_run, tmp_path / "frames", "--idle-seconds", "0.5")
    assert '"reason": "idle for 0.5 s"' in server.finish(timeout=60)


@pytest.mark.skipif(sys.platform == "win32", reason="kill -9 of the parent is POSIX's")
def test_the_server_ends_with_its_parent_killed(trained_run, tmp_path):
    """The add-on's Blender killed (kill -9): the server's stdin closes, it removes its frame
    file and exits; no orphan stays."""
    frames = tmp_path / "frames"
    frames.mkdir()
    parent = textwrap.dedent(f"""
        import subprocess, sys, time
        from nerf_contract import commands, view_frames
        argv = commands.serve_argv({str(trained_run)!r}, {str(frames)!r}, device="cpu")
        server = subprocess.Popen(commands.backend_command(sys.executable, argv), stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True)
        server.stdout.readline()  # ready
        server.stdin.write(view_frames.render_request(1, view_matrix=view_frames.IDENTITY,
                           projection_matrix={orthographic(2.0, 2.0)!r}, width=64, height=64) + "\\n")
        server.stdin.flush()
        server.stdout.readline()  # its frame: the frame file exists now
        print(server.pid, flush=True)
        time.sleep(600)
    """)
    process = subprocess.Popen([sys.executable, "-c", parent], cwd=REPO_ROOT, stdout=subprocess.PIPE, text=True)
    server_pid = int(process.stdout.readline())
    assert len(list(frames.iterdir())) == 1
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and _alive(server_pid):
        time.sleep(0.1)
    assert not _alive(server_pid), "the server outlived its parent"
    assert not any(frames.iterdir()), "the server left its frame file"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie (exited, not yet reaped by init) counts as gone.
    status = Path(f"/proc/{pid}/status")
    return not (status.exists() and "State:\tZ" in status.read_text())


def _processes_with(text: bytes) -> list[str]:
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if text in cmdline.read_bytes():
                found.append(cmdline.parent.name)
        except OSError:  # it ended meanwhile
            continue
    return found


@pytest.mark.parametrize("beside", (False, True), ids=("alone", "beside-training"))
def test_bench_view_times_the_server_as_the_add_on_uses_it(trained_marched_run, tmp_path, beside):
    """``bench-view``: the real server orbited at a quarter of the size in drafts, then the
    whole frame, a draft and exact, and the trade of march steps against the exact frame; with
    ``--beside-training``, while a real training runs (and is gone afterwards)."""
    from nerf_backend.bench.view_speed import STEP_SCALES

    result = run_python("-m", "nerf_backend", "bench-view", str(trained_marched_run), "--size", "32", "--frames", "3",
                        "--device", "cpu", "--out", str(tmp_path / "bench"), *(["--beside-training"] if beside else []))
    report = json.loads((tmp_path / "bench" / "view_speed.json").read_text())
    assert report["training_beside_threads"] == (max(1, os.cpu_count() - 1) if beside else None)
    if beside:
        assert "training beside it on" in result.stdout
        assert not _processes_with(b"training_beside"), "the training beside was left running"
    assert report["region"] == [32, 32] and report["orbit_size"] == [8, 8] and report["orbit"]["frames"] == 3
    assert 0 < report["orbit"]["render_median_seconds"] <= report["orbit"]["median_seconds"]
    assert 0 < report["full_frame"]["render_seconds"] <= report["full_frame"]["seconds"]
    assert 0 < report["full_frame"]["exact_render_seconds"] <= report["full_frame"]["exact_seconds"]
    assert "frames a second" in result.stdout and report["start_seconds"] > 0
    trade = {row["step_scale"]: row for row in report["step_trade"]}
    assert tuple(trade) == STEP_SCALES and all(row["pixels_compared"] > 0 for row in trade.values())
    assert trade[1.0]["psnr_against_exact"] is None  # the exact frame again: the same pixels
    assert 25.0 < trade[view_frames.DRAFT_STEP_SCALE]["psnr_against_exact"] and "| ×2 |" in result.stdout, result.stdout


def test_the_add_ons_client_draws_newest_first_and_says_when_the_server_was_killed(trained_run, test_view):
    """addon/core/live_view.py (plain Python, as Blender's timer drives it): frames arrive, an older
    one is never handed out after a newer, a server killed with SIGKILL is reported with no
    frame drawn after it, a restart works, and stopping leaves no process and no files."""
    from addon.core.live_view import LiveViewClient
    intrinsics, pose = test_view
    view = torch.linalg.inv(pose.double()).tolist()
    client = LiveViewClient()
    client.start(sys.executable, REPO_ROOT, trained_run, device="cpu")
    folder = client._folder

    def frame_for(width, height):  # F12's way: one frame, waited for
        return client.render(view, perspective(intrinsics, width, height), width, height, timeout=120)

    frame = frame_for(24, 16)
    assert (frame.width, frame.height, len(frame.rgba), len(frame.depth)) == (24, 16, 24 * 16 * 16, 24 * 16 * 4)
    assert client.state() == "ready"
    assert client.poll_frame() is None, "a frame is handed out once"
    with pytest.raises(RuntimeError, match="view_matrix must be a 4×4 matrix of finite numbers"):
        client.render([[1.0, 0.0], [0.0, 1.0]], perspective(intrinsics, 8, 8), 8, 8, timeout=120)
    server = client._process
    os.kill(server.pid, signal.SIGKILL)
    server.wait()
    assert client.state().startswith("stopped: ") and "killed" in client.state()
    assert client.request(view, perspective(intrinsics, 8, 8), 8, 8) is None and client.poll_frame() is None
    with pytest.raises(RuntimeError, match=r"not running \(stopped: the server was killed \(signal 9\)\)"):
        frame_for(8, 8)
    client.start(sys.executable, REPO_ROOT, trained_run, device="cpu")  # the panel's click restarts it
    assert not folder.exists(), "the killed server's folder is removed at the restart"
    assert frame_for(8, 8).width == 8
    pid, folder = client._process.pid, client._folder
    client.stop()
    assert client.state() == "off" and not folder.exists() and not _alive(pid)


def test_the_scheduler_serves_moving_views_first_then_every_view_in_turn():
    """Several 3D Views: one request in flight; a moving view gets quarter-size drafts before
    any other is served; at rest every view gets its whole region in turn, a draft and then
    exact; a frame is filed with the view it was asked for, and a region that goes is forgotten."""
    from addon.core.live_view import EXACT, MOVING, REST_SECONDS, RESTING_DRAFT, LiveFrame, ViewScheduler
    from nerf_contract.view_frames import DRAFT_STEP_SCALE

    def frame(request_id, request):
        return LiveFrame(request_id, request.width, request.height, b"", b"", 0.01, 0)

    eye = np.eye(4).tolist()
    moved = np.eye(4)
    moved[0, 3] = 0.5  # the view slid sideways
    moved = moved.tolist()
    scheduler = ViewScheduler()
    for key in ("a", "b", "c"):
        scheduler.update(key, eye, eye, 401, 300, now=0.0)
    served, now = [], 1.0
    for request_id in range(1, 7):  # at rest: each of the three, whole, in turn: drafts, then exact
        request = scheduler.next_request(now)
        scheduler.sent(request_id, request, now)
        assert scheduler.next_request(now) is None  # one at a time
        assert scheduler.delivered(frame(request_id, request)) == request.key
        served.append((request.key, request.width, request.height, request.stage, request.step_scale))
    drafts = [(key, 401, 300, RESTING_DRAFT, DRAFT_STEP_SCALE) for key in "abc"]
    assert sorted(served[:3]) == drafts and sorted(served[3:]) == [(key, 401, 300, EXACT, 1.0) for key in "abc"]
    assert scheduler.next_request(now) is None  # every view is exact
    scheduler.update("b", moved, eye, 401, 300, now=now)  # b's view moves
    request = scheduler.next_request(now + 0.01)
    assert (request.key, request.width, request.height, request.stage) == ("b", 101, 75, MOVING)
    assert request.step_scale == DRAFT_STEP_SCALE
    scheduler.sent(10, request, now)
    scheduler.update("b", eye, eye, 401, 300, now=now + 0.05)  # moved again before the frame came
    assert scheduler.delivered(frame(10, request)) == "b"
    assert scheduler.regions["b"].frame_signature != scheduler.regions["b"].signature  # drawn, yet stale
    request = scheduler.next_request(now + 0.06)
    assert (request.key, request.stage) == ("b", MOVING)  # still moving: a quarter frame of the new view
    scheduler.sent(11, request, now)
    scheduler.failed([11])  # refused by the server: the next may go
    request = scheduler.next_request(now + 0.05 + REST_SECONDS)
    assert (request.key, request.stage, request.width) == ("b", RESTING_DRAFT, 401)  # at rest: the whole region
    scheduler.sent(12, request, now)
    scheduler.keep_only({"a", "c"})  # b's area closed meanwhile
    assert scheduler.delivered(frame(12, request)) is None and set(scheduler.regions) == {"a", "c"}


def test_a_frame_goes_to_the_compositor_linear_premultiplied_with_empty_far_away():
    """addon/core/composite_pixels.py (F12's images): the frame's sRGB colour decoded to linear (the
    IEC 61966-2-1 curve: 0.5 → 0.21404, 0.04045 → 0.0031308) under its alpha, and depth where
    the NeRF is empty (infinite, or no opacity) far behind any render's background."""
    from addon.core.composite_pixels import EMPTY_DEPTH, compositor_pixels
    from addon.core.live_view import LiveFrame

    straight = np.array([[0.5, 1.0, 0.04045], [0.5, 0.0, 1.0], [0.2, 0.2, 0.2], [0.7, 0.7, 0.7]])
    alpha = np.array([1.0, 0.5, 0.0, 0.25])
    rgba = np.concatenate([straight * alpha[:, None], alpha[:, None]], axis=1).astype(np.float32)
    depth = np.array([3.0, 4.0, 5.0, np.inf], np.float32)
    colour, z = compositor_pixels(LiveFrame(7, 2, 2, rgba.tobytes(), depth.tobytes(), 0.1, 0))
    colour, z = colour.reshape(4, 4), z.reshape(4, 4)
    np.testing.assert_allclose(colour[0], [0.21404, 1.0, 0.0031308, 1.0], atol=2e-5)
    np.testing.assert_allclose(colour[1], [0.5 * 0.21404, 0.0, 0.5, 0.5], atol=2e-5)  # premultiplied again
    np.testing.assert_array_equal(colour[2], [0.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(z[:, 0], np.float32([3.0, 4.0, EMPTY_DEPTH, EMPTY_DEPTH]))
    assert (z[:, 0] == z[:, 1]).all() and (z[:, 3] == 1.0).all() and colour.dtype == z.dtype == np.float32
