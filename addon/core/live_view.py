"""The add-on's side of the live view: it starts ``serve`` in the backend's Python, sends it the
views to draw and hands the newest frame to the viewport's drawing (``nerf_contract.view_frames``:
the requests, events and frame files). Plain Python, no bpy and no torch, so tests drive it
without Blender; Blender's timer calls ``poll_frame`` on the main thread.

A thread reads the server's events as they come (the pipe never fills, Blender never waits on
it); the frames stay in the folder this client makes and removes.

Example (with a trained run):
    client = LiveViewClient()
    client.start(python, backend_root, run, device="cpu")
    client.request(view_matrix, projection_matrix, 200, 150)
    frame = client.poll_frame()   # None until a frame newer than the last one handed out is there
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from nerf_contract import commands, view_frames
from nerf_contract.run_layout import CHECKPOINT_NAME

LOG_NAME = "serve.log"  # the server's stderr, in the frames folder: why it stopped


@dataclass(frozen=True)
class LiveFrame:
    request_id: int
    width: int
    height: int
    rgba: bytes  # float32 RGBA, premultiplied, rows bottom to top
    depth: bytes  # float32 camera z, +inf where empty
    seconds: float  # the server's render time
    iteration: int  # the checkpoint's


def cannot_serve(python: str, run: Path) -> str:
    """Why ``run`` cannot be served yet with the backend's ``python`` ("" where it can): the
    live view's and NeRF in Renders' answer to a press."""
    if not python:
        return "no backend Python: press Set Up Backend, or choose one in the preferences"
    if not (Path(run) / CHECKPOINT_NAME).is_file():
        return f"{run}: no checkpoint yet: train first (a run still training is served from its first checkpoint)"
    return ""


def frames_parent() -> str | None:
    """Where the frames folder goes: memory (/dev/shm) where the system has it, else the temp folder."""
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


class LiveViewClient:
    def __init__(self) -> None:
        self._process: subprocess.Popen | None = None
        self._folder: Path | None = None
        self._lock = threading.Lock()
        self._newest: dict | None = None  # the newest frame event not handed out yet
        self._handed_out = -1  # the request id of the last frame handed out: never an older one after it
        self._next_id = 0
        self._failed: list[int] = []  # request ids the server answered with an error
        self._files: dict[str, view_frames.FrameFile] = {}
        self.ready: dict | None = None
        self.exit_reason: str | None = None
        self.last_error: str = ""

    # --- the process ---------------------------------------------------------------------

    def start(self, python: str, backend_root: Path, run: Path, device: str = "auto",
              idle_seconds: float | None = None) -> None:
        self.stop()
        self._folder = Path(tempfile.mkdtemp(prefix="nerf_view_", dir=frames_parent()))
        command = commands.backend_command(python, commands.serve_argv(str(run), str(self._folder), device=device,
                                                                       idle_seconds=idle_seconds))
        env = dict(os.environ, PYTHONPATH=str(backend_root), PYTHONUNBUFFERED="1")
        with open(self._folder / LOG_NAME, "w", encoding="utf-8") as log:
            self._process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log,
                                             text=True, env=env)
        self.ready, self.exit_reason, self.last_error = None, None, ""
        self._newest, self._handed_out, self._failed = None, -1, []
        threading.Thread(target=self._read_events, args=(self._process,), daemon=True).start()

    def _read_events(self, process: subprocess.Popen) -> None:
        for line in process.stdout:
            event = view_frames.parse_event(line)
            if event is None:
                continue
            with self._lock:
                kind = event["event"]
                if kind == view_frames.READY:
                    self.ready = event
                elif kind == view_frames.FRAME:
                    self._newest = event
                elif kind == view_frames.ERROR:
                    self.last_error = event.get("message", "")
                    if isinstance(event.get("id"), int):
                        self._failed.append(event["id"])
                elif kind == view_frames.EXIT:
                    self.exit_reason = event.get("reason", "")

    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def state(self) -> str:
        """``off``, ``starting``, ``ready``, or ``stopped: WHY`` (the server's reason, or the
        last line of its output where it died without one: killed, or an error)."""
        if self._process is None:
            return "off"
        if self.running():
            return "ready" if self.ready is not None else "starting"
        reason = self.exit_reason
        code = self._process.returncode
        if not reason and code is not None and code < 0:
            reason = f"the server was killed (signal {-code})"
        if not reason:
            log = self._folder / LOG_NAME if self._folder else None
            tail = log.read_text(errors="replace").strip().splitlines()[-1:] if log and log.is_file() else []
            code = self._process.returncode
            reason = tail[0] if tail else f"the server ended (exit status {code}{', killed' if code and code < 0 else ''})"
        return f"stopped: {reason}"

    def stop(self) -> None:
        """Asks the server to quit (killed if it has not within 5 s) and removes the frames."""
        for frames in self._files.values():
            frames.close()
        self._files.clear()
        if self._process is not None:
            if self._process.poll() is None:
                try:
                    self._process.stdin.write(view_frames.quit_request() + "\n")
                    self._process.stdin.close()
                except OSError:
                    pass
                try:
                    self._process.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self._process.kill()
                    self._process.wait()
            self._process = None
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None

    # --- frames --------------------------------------------------------------------------

    def request(self, view_matrix, projection_matrix, width: int, height: int, nerf_to_world=None,
                step_scale: float = 1.0) -> int | None:
        """Asks for a frame (``step_scale``: a draft's march step, ``view_frames``'s); its
        request id, or None where the server is not running."""
        if not self.running():
            return None
        self._next_id += 1
        line = view_frames.render_request(self._next_id, view_matrix=view_matrix, projection_matrix=projection_matrix,
                                          width=width, height=height, nerf_to_world=nerf_to_world,
                                          step_scale=step_scale)
        try:
            self._process.stdin.write(line + "\n")
            self._process.stdin.flush()
        except OSError:
            return None  # it died meanwhile: state() says why
        return self._next_id

    def render(self, view_matrix, projection_matrix, width: int, height: int, nerf_to_world=None,
               timeout: float = 600.0) -> LiveFrame:
        """One frame, waited for: what F12 asks (the render waits for the NeRF as for the rest of
        the scene). RuntimeError with the reason where the server refused it, stopped or took
        longer than ``timeout`` seconds."""
        request_id = self.request(view_matrix, projection_matrix, width, height, nerf_to_world=nerf_to_world)
        if request_id is None:
            raise RuntimeError(f"the render server is not running ({self.state()})")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if request_id in self.take_failed():
                raise RuntimeError(self.last_error)
            frame = self.poll_frame()
            if frame is not None and frame.request_id == request_id:
                return frame
            if not self.running():
                raise RuntimeError(f"the render server {self.state()}")
            time.sleep(0.005)
        raise RuntimeError(f"the render server sent no frame within {timeout:.0f} s")

    def take_failed(self) -> list[int]:
        """The request ids the server refused since the last call (each with ``last_error``)."""
        with self._lock:
            failed, self._failed = self._failed, []
        return failed

    def poll_frame(self) -> LiveFrame | None:
        """The newest frame not handed out yet, copied out of its file; None where there is none,
        where it is older than one handed out already, or where the server overwrote it while
        it was read (a newer one is on its way). Nothing once the server has stopped: its files
        are gone or stale."""
        with self._lock:
            event, self._newest = self._newest, None
        if event is None or not self.running() or event["id"] <= self._handed_out:
            return None
        frames = self._files.get(event["file"])
        if frames is None:
            for old in self._files.values():  # the server moved to a larger file
                old.close()
            try:
                frames = view_frames.FrameFile.open(event["file"])
            except (OSError, ValueError):
                return None
            self._files = {event["file"]: frames}
        copied = frames.read(event["slot"], event["sequence"])
        if copied is None:
            return None
        width, height, rgba, depth = copied
        self._handed_out = event["id"]
        return LiveFrame(event["id"], width, height, rgba, depth, event["seconds"], event["iteration"])


# --- which view gets the next frame ----------------------------------------------------------

MOVING_DIVISOR = 4  # while the view moves: a quarter of the region's side (1/16 of its pixels)
REST_SECONDS = 0.25  # a view unchanged this long has come to rest: the whole region is drawn
LOST_SECONDS = 60.0  # a request unanswered this long is given up (the server restarted, or hung)
# A view's frames in turn: a quarter-size draft while it moves, then at rest the whole region as
# a draft (on a CPU, within about a second of resting) and then exact. A frame of a later stage
# never gives way to an earlier one of the same view.
MOVING, RESTING_DRAFT, EXACT = 1, 2, 3


def _rounded(matrix) -> tuple:
    return tuple(tuple(round(float(value), 6) for value in row) for row in matrix)


@dataclass
class RegionView:
    """One 3D View's region as last drawn, and the newest frame it got."""

    view_matrix: tuple
    projection_matrix: tuple
    width: int
    height: int
    nerf_to_world: tuple | None
    changed_at: float
    frame: LiveFrame | None = None
    frame_signature: tuple | None = None  # the view the frame was rendered for
    frame_stage: int = 0  # MOVING, RESTING_DRAFT or EXACT: how far the frame came

    @property
    def signature(self) -> tuple:
        return self.view_matrix, self.projection_matrix, self.width, self.height, self.nerf_to_world

    def wants(self, now: float) -> int | None:
        """The stage of frame this region needs next, or None where its frame is as good as
        it gets for now."""
        resting = now - self.changed_at >= REST_SECONDS
        current = self.frame_signature == self.signature
        if not resting:
            return None if current else MOVING
        if current and self.frame_stage >= RESTING_DRAFT:
            return None if self.frame_stage == EXACT else EXACT
        return RESTING_DRAFT

    def size(self, stage: int) -> tuple[int, int]:
        if stage == MOVING:
            return max(1, -(-self.width // MOVING_DIVISOR)), max(1, -(-self.height // MOVING_DIVISOR))
        return self.width, self.height


@dataclass(frozen=True)
class ViewRequest:
    key: object
    view_matrix: tuple
    projection_matrix: tuple
    width: int
    height: int
    nerf_to_world: tuple | None
    signature: tuple
    stage: int

    @property
    def step_scale(self) -> float:
        return 1.0 if self.stage == EXACT else view_frames.DRAFT_STEP_SCALE


class ViewScheduler:
    """Which 3D View the server renders next, and how: one request in flight at a time (a
    frame is rendered for the view as it is when the server gets to it, never queued behind
    stale ones), a quarter of the region's side as a draft while its view moves, the whole
    region once it has rested for REST_SECONDS, first as a draft and then exact; moving views
    first, then the others in turn, so several 3D Views all get drawn. Plain Python: the
    viewport's draw handler reports each region's view, Blender's timer asks for the next
    request and hands back the frames.

    Example:
        >>> scheduler = ViewScheduler()
        >>> identity = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
        >>> scheduler.update("view", identity, identity, 400, 300, now=0.0)
        >>> request = scheduler.next_request(now=0.1)
        >>> request.width, request.height, request.step_scale   # moving: a quarter of each side, a draft
        (100, 75, 2.0)
        >>> scheduler.sent(1, request, now=0.1)
        >>> scheduler.next_request(now=0.2) is None   # one in flight at a time
        True
        >>> scheduler.delivered(LiveFrame(1, 100, 75, b"", b"", 0.05, 0))
        'view'
        >>> rest = scheduler.next_request(now=0.5)   # at rest: the whole region, a draft first
        >>> rest.width, rest.step_scale
        (400, 2.0)
        >>> scheduler.sent(2, rest, now=0.5); _ = scheduler.delivered(LiveFrame(2, 400, 300, b"", b"", 0.5, 0))
        >>> scheduler.next_request(now=1.1).step_scale   # then exact
        1.0
    """

    def __init__(self) -> None:
        self.regions: dict[object, RegionView] = {}
        self._in_flight: tuple[int, ViewRequest, float] | None = None
        self._turn = 0

    def update(self, key, view_matrix, projection_matrix, width: int, height: int, now: float,
               nerf_to_world=None) -> None:
        """The region's view as it is drawn now (called on every redraw; cheap when unchanged)."""
        signature = (_rounded(view_matrix), _rounded(projection_matrix), int(width), int(height),
                     None if nerf_to_world is None else _rounded(nerf_to_world))
        region = self.regions.get(key)
        if region is None:
            self.regions[key] = RegionView(*signature, changed_at=now)
        elif region.signature != signature:
            (region.view_matrix, region.projection_matrix, region.width, region.height,
             region.nerf_to_world) = signature
            region.changed_at = now

    def keep_only(self, keys) -> None:
        """Forgets regions that are gone (an area closed, a window or file changed)."""
        for key in set(self.regions) - set(keys):
            del self.regions[key]

    def clear(self) -> None:
        self.regions.clear()
        self._in_flight = None

    def next_request(self, now: float) -> ViewRequest | None:
        if self._in_flight is not None:
            if now - self._in_flight[2] < LOST_SECONDS:
                return None
            self._in_flight = None
        keys = list(self.regions)
        if not keys:
            return None
        order = keys[self._turn % len(keys):] + keys[:self._turn % len(keys)]
        moving = [key for key in order if now - self.regions[key].changed_at < REST_SECONDS]
        for key in moving + [key for key in order if key not in moving]:
            region = self.regions[key]
            stage = region.wants(now)
            if stage is not None:
                self._turn = keys.index(key) + 1
                width, height = region.size(stage)
                return ViewRequest(key, region.view_matrix, region.projection_matrix, width, height,
                                   region.nerf_to_world, region.signature, stage)
        return None

    def sent(self, request_id: int, request: ViewRequest, now: float) -> None:
        self._in_flight = (request_id, request, now)

    def failed(self, request_ids) -> None:
        """The server refused these requests: the next one may go."""
        if self._in_flight is not None and self._in_flight[0] in request_ids:
            self._in_flight = None

    def delivered(self, frame: LiveFrame):
        """Files ``frame`` with the region it was rendered for; that region's key, or None
        (the region is gone, or the frame answers no request in flight)."""
        if self._in_flight is None or self._in_flight[0] != frame.request_id:
            return None
        _, request, _ = self._in_flight
        self._in_flight = None
        region = self.regions.get(request.key)
        if region is None:
            return None
        region.frame, region.frame_signature, region.frame_stage = frame, request.signature, request.stage
        return request.key
