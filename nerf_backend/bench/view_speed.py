"""``bench-view RUN``: how fast the live view answers, measured as the add-on uses it: the real
``serve`` process, its pipes and its frame files. First the view at rest, untimed (what the
add-on draws when the live view is turned on: the frame file grows to the region's size).
Then a camera orbits the scene at a fraction of the frame's size as drafts (the add-on's
frames while the view moves, at ``DRAFT_STEP_SCALE``; each request sent when the frame before
it is read), then rests and asks for the whole frame, a draft and then exact. Then the trade: the resting view's whole frame at each march step of
``STEP_SCALES``, its time and its PSNR against the exact frame.

With ``beside_training``, a real ``train`` runs on the run's dataset the whole time, on all
cores but one as the add-on starts it: the live view of one run while another trains.

Reported: the server's start (spawned to ready: torch's import, the model's load and its
renderer's caches), each orbit frame from request to pixels copied out of the frame file
(what a frame costs the add-on's timer, upload and drawing apart) and the frames a second that
makes, the whole frame's time after the rest (draft, and exact after it) and the trade's table.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from nerf_contract import commands, view_frames
from nerf_contract.run_layout import EVENTS_NAME
from nerf_contract.training_events import read_events

from ..configs.train_config import TrainConfig
from ..core.devices import machine_record, machine_words
from ..core.errors import NerfError
from ..core.files import write_json
from ..data.dataset import load_scene_bounds, load_split
from ..data.run_folder import RunFolder
from ..model_components.ray_bounds import PROTOCOL_BOX, choose_ray_bounds

NEAR, FAR = 0.05, 1000.0
# The march steps of the trade's table, as multiples of the model's (1: exact).
STEP_SCALES = (1.0, 1.5, view_frames.DRAFT_STEP_SCALE, 3.0)


def orbit_view(centre: torch.Tensor, radius: float, azimuth: float, elevation: float) -> torch.Tensor:
    """World-to-camera matrix of a camera on a sphere around ``centre`` looking at it, +Z up
    (Blender's world).

    Example:
        >>> view = orbit_view(torch.zeros(3), 4.0, 0.0, 0.0)
        >>> (view @ torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)).tolist()  # 4 ahead
        [0.0, 0.0, -4.0, 1.0]
    """
    eye = centre.double() + radius * torch.tensor([math.cos(elevation) * math.cos(azimuth),
                                                   math.cos(elevation) * math.sin(azimuth), math.sin(elevation)],
                                                  dtype=torch.float64)
    back = torch.nn.functional.normalize(eye - centre.double(), dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                                                             back), dim=0)
    up = torch.linalg.cross(back, right)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up, back, eye
    return torch.linalg.inv(pose)


def projection(fl_x: float, fl_y: float, width: int, height: int) -> list[list[float]]:
    """OpenGL's projection of a centred pinhole camera of focal lengths ``fl_x, fl_y`` (pixels)
    at ``width × height``: the same at any size it is drawn at."""
    return [[2 * fl_x / width, 0.0, 0.0, 0.0], [0.0, 2 * fl_y / height, 0.0, 0.0],
            [0.0, 0.0, -(FAR + NEAR) / (FAR - NEAR), -2 * FAR * NEAR / (FAR - NEAR)], [0.0, 0.0, -1.0, 0.0]]


class _Server:
    def __init__(self, run: Path, frames: Path, device: str):
        start = time.perf_counter()
        self.log = frames / "serve.log"  # its stderr: the line it stops with, or its error
        with open(self.log, "w") as log:
            self.process = subprocess.Popen(commands.backend_command(sys.executable, commands.serve_argv(
                str(run), str(frames), device=device)), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log,
                text=True)
        self.ready = self.event()
        self.start_seconds = time.perf_counter() - start

    def event(self) -> dict:
        line = self.process.stdout.readline()
        event = view_frames.parse_event(line)
        if event is None or event["event"] in (view_frames.ERROR, view_frames.EXIT):
            self.process.kill()
            self.process.wait()
            said = self.log.read_text().strip().splitlines()[-1:] or [line.strip()]
            raise NerfError(f"bench-view: the server stopped: {said[0]}")
        return event

    def frame(self, request: str) -> tuple[float, float, np.ndarray]:
        """Seconds from request to pixels copied, the server's own render seconds and the
        frame's RGBA ``[H·W, 4]``."""
        start = time.perf_counter()
        self.process.stdin.write(request + "\n")
        self.process.stdin.flush()
        event = self.event()
        while event["event"] != view_frames.FRAME:
            event = self.event()
        frames = view_frames.FrameFile.open(event["file"])
        copied = frames.read(event["slot"], event["sequence"])
        frames.close()
        if copied is None:
            raise NerfError("bench-view: a frame was overwritten before it was read")
        seconds = time.perf_counter() - start
        return seconds, event["seconds"], np.frombuffer(copied[2], np.float32).reshape(-1, 4)

    def stop(self) -> None:
        self.process.stdin.close()
        self.process.wait(timeout=60)


@contextlib.contextmanager
def training_beside(dataset: str, folder: Path, device: str):
    """A real ``train`` on ``dataset`` (``auto``, all cores but one: the add-on's choice) from
    its first step until the block ends; yields its thread count."""
    threads = max(1, (os.cpu_count() or 2) - 1)
    run = folder / "training_beside"
    argv = commands.train_argv(dataset, str(run), device=device, preset="auto", max_seconds=24 * 3600,
                               cpu_threads=threads)
    with open(folder / "train.log", "w") as log:
        process = subprocess.Popen(commands.backend_command(sys.executable, argv), stdout=subprocess.DEVNULL, stderr=log)
    try:
        deadline = time.monotonic() + 600
        while not (run / EVENTS_NAME).is_file() or not read_events(run / EVENTS_NAME):
            if process.poll() is not None or time.monotonic() > deadline:
                said = (folder / "train.log").read_text().strip().splitlines()[-1:] or ["no output"]
                raise NerfError(f"bench-view: the training beside did not start: {said[0]}")
            time.sleep(0.5)
        yield threads
    finally:
        process.kill()
        process.wait()


def view_speed(run: Path, out_dir: Path, size: int | None = None, fraction: float = 0.25, frames: int = 30,
               device: str = "cpu", beside_training: bool = False) -> dict:
    """Times the live view of ``run`` (see the module's text); writes ``view_speed.json`` and
    ``view_speed.md`` into ``out_dir``."""
    stored = RunFolder(run).read_config()
    test = load_split(stored["dataset"], "test")
    intrinsics = test.intrinsics
    width = size or intrinsics.width
    height = round(width * intrinsics.height / intrinsics.width)
    config = TrainConfig.from_dict(stored["config"])
    box = choose_ray_bounds(config.ray_bounds, load_scene_bounds(stored["dataset"]))[0].box or PROTOCOL_BOX
    centre = torch.tensor([(low + high) / 2 for low, high in zip(box.box_min, box.box_max)])
    radius = float((test.poses[:, :3, 3] - centre).norm(dim=-1).mean())
    fl_x, fl_y = intrinsics.fl_x * width / intrinsics.width, intrinsics.fl_y * height / intrinsics.height
    small = (max(1, round(width * fraction)), max(1, round(height * fraction)))
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="nerf_view_") as folder, contextlib.ExitStack() as beside:
        training_threads = beside.enter_context(training_beside(stored["dataset"], Path(folder), device)) \
            if beside_training else None
        server = _Server(run, Path(folder), device)

        request_ids = itertools.count()
        rest_view = orbit_view(centre, radius, 0.0, math.radians(30)).tolist()

        whole_projection = projection(fl_x, fl_y, width, height)

        def whole(scale: float) -> tuple[float, float, np.ndarray]:
            return server.frame(view_frames.render_request(next(request_ids), view_matrix=rest_view, width=width,
                                                           height=height, projection_matrix=whole_projection,
                                                           step_scale=scale))

        for scale in (view_frames.DRAFT_STEP_SCALE, 1.0):  # untimed: the add-on's first frames, of the view at rest
            whole(scale)
        orbit = []
        for index in range(frames + 1):  # the first is a warm-up, untimed
            view = orbit_view(centre, radius, 2 * math.pi * index / frames, math.radians(30)).tolist()
            request = view_frames.render_request(next(request_ids), view_matrix=view, projection_matrix=projection(
                fl_x, fl_y, width, height), width=small[0], height=small[1], step_scale=view_frames.DRAFT_STEP_SCALE)
            timing = server.frame(request)
            if index:
                orbit.append(timing)
        draft = whole(view_frames.DRAFT_STEP_SCALE)
        exact = whole(1.0)
        trade = [_trade_row(scale, whole(scale), exact[2]) for scale in STEP_SCALES]
        server.stop()
    seconds = [total for total, _, _ in orbit]
    report = {
        "run": str(Path(run).resolve()), "device": device, "machine": machine_record(torch.device(device)),
        "iteration": server.ready.get("iteration"), "region": [width, height], "orbit_size": list(small),
        "start_seconds": server.start_seconds, "training_beside_threads": training_threads,
        "draft_step_scale": view_frames.DRAFT_STEP_SCALE,
        "orbit": {"frames": frames, "median_seconds": statistics.median(seconds), "slowest_seconds": max(seconds),
                  "frames_per_second": 1.0 / statistics.median(seconds),
                  "render_median_seconds": statistics.median(render for _, render, _ in orbit)},
        "full_frame": {"seconds": draft[0], "render_seconds": draft[1], "exact_seconds": exact[0],
                       "exact_render_seconds": exact[1]},
        "step_trade": trade,
    }
    write_json(out_dir / "view_speed.json", report)
    (out_dir / "view_speed.md").write_text(view_speed_markdown(report))
    return report


def _trade_row(scale: float, frame: tuple[float, float, np.ndarray], exact: np.ndarray) -> dict:
    """One row of the trade: the frame's time, and its PSNR against the exact frame over the
    pixels where either has the NeRF (premultiplied colour; empty pixels would flatter it);
    None where the two are the same frame."""
    seconds, render_seconds, rgba = frame
    seen = np.maximum(rgba[:, 3], exact[:, 3]) > 1e-3
    error = float(np.mean((rgba[seen, :3] - exact[seen, :3]) ** 2)) if seen.any() else 0.0
    return {"step_scale": scale, "seconds": seconds, "render_seconds": render_seconds,
            "psnr_against_exact": 10 * math.log10(1.0 / error) if error > 0 else None,
            "pixels_compared": int(seen.sum())}


def view_speed_markdown(report: dict) -> str:
    width, height = report["region"]
    orbit, full = report["orbit"], report["full_frame"]
    draft = f"×{report['draft_step_scale']:g} step"
    lines = [
        f"# bench-view: {report['run']} (iteration {report['iteration']})", "",
        f"{report['device']}, {machine_words(report['machine'])}; region {width}×{height}, orbit frames "
        f"{report['orbit_size'][0]}×{report['orbit_size'][1]} (drafts: the march's {draft})"
        + (f"; training beside it on {report['training_beside_threads']} thread(s)."
           if report.get("training_beside_threads") else "."), "",
        "| what | seconds | |", "| --- | ---: | --- |",
        f"| server start (spawn to ready) | {report['start_seconds']:.2f} | |",
        f"| orbit frame, request to pixels (median of {orbit['frames']}) | {orbit['median_seconds']:.3f} | "
        f"{orbit['frames_per_second']:.1f} frames a second; slowest {orbit['slowest_seconds']:.3f} s; "
        f"rendering {orbit['render_median_seconds']:.3f} s |",
        f"| whole frame after the rest, draft ({draft}) | {full['seconds']:.3f} | rendering "
        f"{full['render_seconds']:.3f} s |",
        f"| whole frame after the rest, exact | {full['exact_seconds']:.3f} | rendering "
        f"{full['exact_render_seconds']:.3f} s |", "",
        f"The trade: the resting view's whole {width}×{height} frame at each march step, against the exact frame "
        "(PSNR over the pixels where either has the NeRF).", "",
        "| march step | seconds | PSNR against exact (dB) |", "| ---: | ---: | ---: |"]
    for row in report["step_trade"]:
        psnr = "the same frame" if row["psnr_against_exact"] is None else f"{row['psnr_against_exact']:.2f}"
        lines.append(f"| ×{row['step_scale']:g} | {row['seconds']:.3f} | {psnr} |")
    return "\n".join(lines + [""])
