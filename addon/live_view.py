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
from dataclasses import dataclass
from pathlib import Path

from nerf_contract import commands, view_frames

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
        self._newest, self._handed_out = None, -1
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

    def request(self, view_matrix, projection_matrix, width: int, height: int, nerf_to_world=None) -> int | None:
        """Asks for a frame; its request id, or None where the server is not running."""
        if not self.running():
            return None
        self._next_id += 1
        line = view_frames.render_request(self._next_id, view_matrix=view_matrix, projection_matrix=projection_matrix,
                                          width=width, height=height, nerf_to_world=nerf_to_world)
        try:
            self._process.stdin.write(line + "\n")
            self._process.stdin.flush()
        except OSError:
            return None  # it died meanwhile: state() says why
        return self._next_id

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
