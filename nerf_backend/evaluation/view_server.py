"""``serve RUN``: a trained model kept loaded, rendering the views a parent process asks for
(the add-on's live view in Blender's viewport). The requests, events and frame files are
``nerf_contract.view_frames``'s; this module is the server's side.

Three parts: ``LatestRequest`` (a one-place mailbox: a new request replaces one that waits),
``LiveModel`` (the run's model, loaded again when training replaces its checkpoint, and one
view rendered from a graphics API's matrices) and ``FrameWriter`` (the frame files). ``serve``
joins them: a thread reads stdin into the mailbox, the main thread renders what it holds.
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Callable

import numpy as np
import torch

from nerf_contract import view_frames as contract

from ..core.cameras import camera_z_along_rays, pixels_seeing_boxes, rays_from_matrices
from ..core.errors import NerfError
from ..core.world_frame import world_to_nerf_matrix
from ..data.dataset import load_scene_profile
from ..data.run_folder import RunFolder
from ..model_components.ray_bounds import PROTOCOL_BOX, RayBounds
from .inference import load_trained_model
from .render_views import render_rays

# A frame's largest side: a 8K display's region; a request beyond it is refused, not rendered.
MAX_SIDE = 8192
# How often the run's checkpoint is looked at for a newer one (a run still training writes one
# every few hundred steps); reloading costs a load of the checkpoint.
RELOAD_CHECK_SECONDS = 2.0
# Opacity below which a pixel has no surface: its depth is +inf (nothing there to occlude).
EMPTY_OPACITY = 1e-4


class Closed(Exception):
    """The server is asked to stop; ``reason`` says why."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class LatestRequest:
    """A mailbox of one: ``put`` replaces a request that still waits (the latest wins), ``take``
    waits for one.

    Example:
        >>> box = LatestRequest()
        >>> box.put({"id": 1}); box.put({"id": 2})
        >>> box.take(timeout=0.1)["id"], box.take(timeout=0.01)
        (2, None)
    """

    def __init__(self):
        self._condition = threading.Condition()
        self._request: dict | None = None
        self._closed: str | None = None

    def put(self, request: dict) -> None:
        with self._condition:
            self._request = request
            self._condition.notify()

    def close(self, reason: str) -> None:
        with self._condition:
            self._closed = self._closed or reason
            self._condition.notify()

    def take(self, timeout: float) -> dict | None:
        """The waiting request (None after ``timeout`` seconds without one); ``Closed`` once
        closed, even with a request waiting."""
        with self._condition:
            self._condition.wait_for(lambda: self._request is not None or self._closed is not None, timeout)
            if self._closed is not None:
                raise Closed(self._closed)
            request, self._request = self._request, None
            return request


def _matrix(request: dict, key: str) -> torch.Tensor:
    value = request.get(key)
    try:
        matrix = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError):
        matrix = None
    if matrix is None or matrix.shape != (4, 4) or not bool(torch.isfinite(matrix).all()):
        raise NerfError(f"request {request.get('id')}: {key} must be a 4×4 matrix of finite numbers")
    return matrix


def checked_request(request: dict) -> dict:
    """The render request with its matrices as tensors; NerfError naming what is wrong."""
    width, height = request.get("width"), request.get("height")
    if not all(isinstance(side, int) and 0 < side <= MAX_SIDE for side in (width, height)):
        raise NerfError(f"request {request.get('id')}: width and height must be whole numbers from 1 to {MAX_SIDE}")
    checked = {"id": request.get("id"), "width": width, "height": height,
               "view": _matrix(request, "view_matrix"), "projection": _matrix(request, "projection_matrix")}
    if request.get("nerf_to_world") is not None:
        checked["nerf_to_world"] = _matrix(request, "nerf_to_world")
    scale = request.get("step_scale", 1.0)
    if not isinstance(scale, (int, float)) or isinstance(scale, bool) or not 1.0 <= scale <= contract.MAX_STEP_SCALE:
        raise NerfError(f"request {request.get('id')}: step_scale must be a number from 1 to "
                        f"{contract.MAX_STEP_SCALE:g}")
    checked["step_scale"] = float(scale)
    if abs(float(torch.linalg.det(checked["projection"] @ checked["view"]))) < 1e-12:
        raise NerfError(f"request {request.get('id')}: the view and projection matrices cannot be inverted")
    return checked


@dataclass
class Frame:
    rgba: np.ndarray  # [H, W, 4] float32, colour premultiplied by alpha, rows bottom to top
    depth: np.ndarray  # [H, W] float32, camera z, +inf where empty, rows bottom to top
    seconds: float


class LiveModel:
    """The run's model on ``device``, loaded again when its checkpoint is replaced."""

    def __init__(self, run: RunFolder, device: torch.device):
        self.run, self.device = run, device
        self._load()  # a run without a checkpoint is an error before the server is ready
        self._signature = self._checkpoint_signature()
        self._checked_at = time.monotonic()

    def _checkpoint_signature(self) -> tuple:
        try:
            stat = os.stat(self.run.checkpoint_path)
        except OSError:
            raise Closed(f"{self.run.checkpoint_path}: the run's checkpoint is gone (the run folder was deleted "
                         "or moved); the live view stops") from None
        return stat.st_mtime_ns, stat.st_size, getattr(stat, "st_ino", 0)

    def _load(self) -> None:
        self.model, self.ray_bounds, state = load_trained_model(self.run, self.device)
        if self.ray_bounds.box is None:  # the protocol's near and far suit its cameras, not a viewport's
            self.ray_bounds = RayBounds(box=PROTOCOL_BOX)
        self.iteration = int(state["iteration"])
        profile = load_scene_profile(self.run.read_config()["dataset"])
        world_to_nerf = world_to_nerf_matrix(profile.get("world_to_nerf") if profile else None)
        self.nerf_to_world = torch.linalg.inv(world_to_nerf)
        self._warm_up()

    def _warm_up(self) -> None:
        """One ray through the box's centre: the renderer's caches (a marched model's
        occupancy for rendering takes seconds on a large grid) are built now, not in the first
        frame the user waits for."""
        box = self.ray_bounds.box
        centre = torch.tensor([(low + high) / 2 for low, high in zip(box.box_min, box.box_max)])
        origin = centre + torch.tensor([0.0, 0.0, 2.0 * max(high - low for low, high in zip(box.box_min, box.box_max))])
        direction = torch.tensor([[0.0, 0.0, -1.0]], device=self.device)
        render_rays(self.model, lambda begin, end: (origin[None].to(self.device), direction), 1, self.ray_bounds)

    def refresh(self) -> bool:
        """Loads the checkpoint again where training replaced it (looked at every
        RELOAD_CHECK_SECONDS at most); True where it did. ``Closed`` where the run is gone;
        NerfError where the new checkpoint does not load (the model loaded before stays)."""
        if time.monotonic() - self._checked_at < RELOAD_CHECK_SECONDS:
            return False
        self._checked_at = time.monotonic()
        signature = self._checkpoint_signature()
        if signature == self._signature:
            return False
        self._signature = signature
        try:
            self._load()
        except (NerfError, OSError, RuntimeError, KeyError) as exc:
            raise NerfError(f"{self.run.path}: the run changed and its checkpoint does not load ({exc}); "
                            "the live view keeps the model it had") from exc
        return True

    def render(self, request: dict) -> Frame:
        """One view of ``checked_request``'s: its rays made in the NeRF's frame (the view
        composed with ``nerf_to_world``, or the dataset's placement), marched at its
        ``step_scale``, colour over black (premultiplied), depth as the camera's z in the world."""
        start = time.perf_counter()
        width, height = request["width"], request["height"]
        # The camera's view of the NeRF's own frame: the rays come out where the model marches.
        nerf_view = request["view"] @ request.get("nerf_to_world", self.nerf_to_world)
        corners = self.model.content_corners()
        # Only the pixels that can see the model's content are rendered; the rest are empty.
        pixels = None if corners is None else pixels_seeing_boxes(corners.cpu(), nerf_view, request["projection"],
                                                                   width, height)
        origins, directions = rays_from_matrices(nerf_view, request["projection"], width, height, pixels)

        def rays(begin: int, end: int) -> tuple[torch.Tensor, torch.Tensor]:
            return origins[begin:end].to(self.device), directions[begin:end].to(self.device)

        with self.model.march_step_scaled(request.get("step_scale", 1.0)):
            rgb, depth, opacity = render_rays(self.model, rays, origins.shape[0], self.ray_bounds, background=0.0)
        hit = opacity > EMPTY_OPACITY
        distance = torch.from_numpy(depth / np.maximum(opacity, EMPTY_OPACITY))
        z = np.where(hit, camera_z_along_rays(nerf_view, origins, directions, distance).numpy(), np.inf)
        rgba = np.concatenate([rgb, opacity[:, None]], axis=1)
        if pixels is not None:
            rgba, z = _scattered(rgba, pixels.numpy(), width * height, 0.0), _scattered(z, pixels.numpy(),
                                                                                       width * height, np.inf)
        rgba = rgba.reshape(height, width, 4)[::-1]
        z = z.astype(np.float32).reshape(height, width)[::-1]
        return Frame(np.ascontiguousarray(rgba), np.ascontiguousarray(z), time.perf_counter() - start)


def _scattered(values: np.ndarray, at: np.ndarray, count: int, fill: float) -> np.ndarray:
    """``values`` (rows) at rows ``at`` of ``count`` rows, ``fill`` elsewhere."""
    whole = np.full((count, *values.shape[1:]), fill, np.float32)
    whole[at] = values
    return whole


class FrameWriter:
    """The frame files in the parent's folder: written slot after slot, a larger file started
    when a frame outgrows the one in use, every file removed at ``close``."""

    def __init__(self, folder: Path):
        if not folder.is_dir():
            raise NerfError(f"{folder}: the frames folder does not exist (the parent makes it)")
        self.folder = folder
        self.file: contract.FrameFile | None = None
        self.number, self.slot = 0, contract.SLOTS - 1

    def write(self, frame: Frame, request_id, iteration: int) -> dict:
        """Writes ``frame`` into the next slot; returns its ``frame`` event."""
        height, width = frame.depth.shape
        if self.file is None or width * height > self.file.capacity:
            self._grow(width * height)
        self.slot = (self.slot + 1) % contract.SLOTS
        sequence = self.file.begin_frame(self.slot)
        start = self.file.slot_offset(self.slot)
        pixels = np.frombuffer(self.file.mapping, np.float32, width * height * 5, start)
        pixels[:width * height * 4] = frame.rgba.reshape(-1)
        pixels[width * height * 4:] = frame.depth.reshape(-1)
        del pixels  # the mapping cannot close while a view of it lives
        self.file.end_frame(self.slot, sequence, request_id if isinstance(request_id, int) else -1, width, height,
                            frame.seconds, iteration)
        return contract.frame_event(request_id, self.file.path, self.slot, sequence, width, height, frame.seconds,
                                    iteration)

    def _grow(self, pixels: int) -> None:
        capacity = max(pixels, 2 * self.file.capacity if self.file else 0, 256 * 256)
        if self.file is not None:
            self.file.remove()
        self.number += 1
        self.file = contract.FrameFile.create(str(self.folder / contract.frame_file_name(self.number)), capacity)
        self.slot = contract.SLOTS - 1

    def close(self) -> None:
        if self.file is not None:
            self.file.remove()
            self.file = None


class EventLine:
    """Events as lines on the server's stdout, from either thread; ``Closed`` once the parent
    stopped reading (a broken pipe)."""

    def __init__(self, stream: IO[str]):
        self.stream, self._lock = stream, threading.Lock()

    def __call__(self, event: dict) -> None:
        with self._lock:
            try:
                self.stream.write(json.dumps(event) + "\n")
                self.stream.flush()
            except (BrokenPipeError, ValueError, OSError):
                raise Closed("its parent stopped reading") from None


def read_requests(stream: IO[str], mailbox: LatestRequest, emit: Callable[[dict], None]) -> None:
    """Reads request lines into ``mailbox`` until ``quit`` or the end of ``stream`` (the parent
    closed its end, or died); a line that is no request gets an ``error`` event."""
    for line in stream:
        if not line.strip():
            continue
        try:
            request = json.loads(line)
        except json.JSONDecodeError:
            request = None
        kind = request.get("request") if isinstance(request, dict) else None
        if kind == contract.QUIT:
            mailbox.close("asked to quit")
            return
        if kind == contract.RENDER:
            mailbox.put(request)
            continue
        try:
            emit(contract.error_event(None, f"not a request: {line.strip()[:200]}"))
        except Closed:
            break
    mailbox.close("its parent closed the request pipe")


def serve(run: RunFolder, frames: Path, device: torch.device, idle_seconds: float,
          requests: IO[str] = sys.stdin, events: IO[str] = sys.stdout) -> str:
    """Serves views until asked to stop, the parent goes, the run goes or ``idle_seconds``
    pass without a request; returns why it stopped (the ``exit`` event's reason)."""
    emit = EventLine(events)
    writer = FrameWriter(frames)
    mailbox = LatestRequest()
    try:
        live = LiveModel(run, device)
        emit(contract.ready_event(str(run.path), str(device), live.iteration, os.getpid(), live.nerf_to_world.tolist()))
        threading.Thread(target=read_requests, args=(requests, mailbox, emit), daemon=True).start()
        reason = _render_requests(live, writer, mailbox, emit, idle_seconds)
    except Closed as closed:
        reason = closed.reason
    finally:
        writer.close()
    try:
        emit(contract.exit_event(reason))
    except Closed:
        pass
    return reason


def _render_requests(live: LiveModel, writer: FrameWriter, mailbox: LatestRequest, emit: Callable[[dict], None],
                     idle_seconds: float) -> str:
    while True:
        request = mailbox.take(timeout=idle_seconds if math.isfinite(idle_seconds) else None)
        if request is None:
            return f"idle for {idle_seconds:g} s"
        try:
            if live.refresh():
                emit(contract.reloaded_event(live.iteration))
            frame = live.render(checked_request(request))
            emit(writer.write(frame, request.get("id"), live.iteration))
        except NerfError as exc:
            emit(contract.error_event(request.get("id"), str(exc)))
