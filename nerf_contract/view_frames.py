"""The live view's contract: what passes between the add-on and ``python -m nerf_backend serve
RUN --frames DIR`` (``commands.serve_argv``), a process that keeps a trained model loaded and
renders the views the add-on asks for.

- **Requests** go down the server's stdin, one JSON object a line (``render_request``,
  ``quit_request``). The latest wins: a request that arrives while a frame renders replaces any
  that waits. The server stops at ``quit``, when its stdin closes (its parent is gone) or after
  ``--idle-seconds`` without a request.
- **Events** come up its stdout, one JSON object a line (``parse_event``): ``ready`` once the
  model is loaded, ``frame`` for each frame written, ``reloaded`` when the run's checkpoint
  changed (a run still training), ``error`` (one line naming the file and the problem) and
  ``exit`` with its reason.
- **Pixels** travel through a memory-mapped frame file in ``DIR`` (``FrameFile``), not the pipe:
  an 800×800 frame is 12.8 MB. The file holds ``SLOTS`` frames; the server writes them in turn,
  and a ``frame`` event names the file, the slot and its sequence number. Each slot's sequence
  is odd while the slot is written: a reader that finds it changed after copying (or odd)
  dropped a frame the server was overwriting, and waits for the next. A frame larger than the
  file holds goes into a new file, which the event names.
- **Drafts**: a request may ask for a march step ``step_scale`` times the model's own
  (``DRAFT_STEP_SCALE``: the add-on's frames while the view moves and its first whole frame
  once it rests, before the exact one), and a draft's rays stop sooner (once 99 % of their
  light is taken); a model that does not march a fixed step ignores it.

A frame is RGBA, float32, colour premultiplied by alpha (alpha is the NeRF's opacity), then
depth, float32: the camera's z (distance along the view axis, in Blender units, not the ray's
length), +inf where the NeRF is empty. Rows run bottom to top, as Blender's images and GPU
textures hold them.

Standard library only (the add-on reads frames inside Blender).

Example:
    >>> line = render_request(3, view_matrix=IDENTITY, projection_matrix=IDENTITY, width=4, height=2)
    >>> sorted(json.loads(line))
    ['height', 'id', 'projection_matrix', 'request', 'view_matrix', 'width']
    >>> parse_event('{"event": "frame", "id": 3, "slot": 1, "sequence": 8}')["slot"]
    1
    >>> parse_event("not json") is None
    True
"""

from __future__ import annotations

import json
import mmap
import os
import struct
from typing import Optional, Sequence

RENDER, QUIT = "render", "quit"
READY, FRAME, RELOADED, ERROR, EXIT = "ready", "frame", "reloaded", "error", "exit"
IDENTITY = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))

FRAME_FILE_PREFIX = "frames-"  # DIR/frames-N.bin, N counting up from 1 as frames outgrow a file
MAGIC = b"NERFVIEW"
VERSION = 1
SLOTS = 3
# The file: a header (magic, version, slots, capacity in pixels), each slot's header (sequence,
# request id, width, height, render seconds, checkpoint iteration) and, from DATA_OFFSET, each
# slot's pixels: capacity × (RGBA + depth) floats.
FILE_HEADER = struct.Struct("<8sIIQ")
SLOT_HEADER = struct.Struct("<QqIIdq")
SLOT_HEADER_OFFSET = 64
DATA_OFFSET = 4096
BYTES_PER_PIXEL = 5 * 4  # RGBA and depth, float32
# The draft frames' march step, as a multiple of the model's (fewer samples, a coarser sum).
# Lego at 800×800 (10-minute model, 2 CPU cores): 2× rendered a frame in 0.63 of the exact
# frame's time, at 31.3 dB against it over the NeRF's pixels, about the model's own error
# against Cycles (bench-view's table has the trade at 1.5, 2 and 3; docs/live_view.md).
DRAFT_STEP_SCALE = 2.0
MAX_STEP_SCALE = 8.0


def render_request(request_id: int, *, view_matrix: Sequence[Sequence[float]],
                   projection_matrix: Sequence[Sequence[float]], width: int, height: int,
                   nerf_to_world: Optional[Sequence[Sequence[float]]] = None, step_scale: float = 1.0) -> str:
    """A request for one frame, as a line (without the newline). ``view_matrix``: world to
    camera, ``projection_matrix``: camera to clip space (Blender's ``RegionView3D.view_matrix``
    and ``window_matrix``, rows as lists); ``nerf_to_world``: where the NeRF's frame sits in the
    world (default: where the dataset's ``world_to_nerf`` took it from); ``step_scale``: the
    march step as a multiple of the model's, 1 (exact) to ``MAX_STEP_SCALE``."""
    request = {"request": RENDER, "id": int(request_id), "view_matrix": [list(map(float, row)) for row in view_matrix],
               "projection_matrix": [list(map(float, row)) for row in projection_matrix],
               "width": int(width), "height": int(height)}
    if nerf_to_world is not None:
        request["nerf_to_world"] = [list(map(float, row)) for row in nerf_to_world]
    if step_scale != 1.0:
        request["step_scale"] = float(step_scale)
    return json.dumps(request)


def quit_request() -> str:
    return json.dumps({"request": QUIT})


# The events, each built here only (their keys are read by the add-on and bench-view):
def ready_event(run: str, device: str, iteration: int, pid: int, nerf_to_world: Sequence[Sequence[float]]) -> dict:
    """The model is loaded. ``nerf_to_world``: where the dataset took the NeRF's frame from (the
    default placement; an add-on moving it with an object composes its matrix with this one)."""
    return {"event": READY, "run": run, "device": device, "iteration": iteration, "pid": pid,
            "nerf_to_world": [list(map(float, row)) for row in nerf_to_world]}


def frame_event(request_id, file: str, slot: int, sequence: int, width: int, height: int, seconds: float,
                iteration: int) -> dict:
    """A frame written: ``file``'s ``slot`` holds it at ``sequence`` (``FrameFile.read``)."""
    return {"event": FRAME, "id": request_id, "file": file, "slot": slot, "sequence": sequence, "width": width,
            "height": height, "seconds": round(seconds, 4), "iteration": iteration}


def reloaded_event(iteration: int) -> dict:
    return {"event": RELOADED, "iteration": iteration}


def error_event(request_id, message: str) -> dict:
    return {"event": ERROR, "id": request_id, "message": message}


def exit_event(reason: str) -> dict:
    return {"event": EXIT, "reason": reason}


def parse_event(line: str) -> Optional[dict]:
    """The event a line of the server's stdout holds, or None (a line that is no event)."""
    try:
        event = json.loads(line)
    except json.JSONDecodeError:
        return None
    return event if isinstance(event, dict) and isinstance(event.get("event"), str) else None


def frame_file_name(number: int) -> str:
    return f"{FRAME_FILE_PREFIX}{number}.bin"


class FrameFile:
    """A frame file mapped into memory: the server creates it (``create``) and writes frames
    (``begin_frame``, then the pixels into ``pixels``, then ``end_frame``); the add-on opens it
    (``open``) and copies frames out (``read``)."""

    def __init__(self, path: str, handle, mapping: mmap.mmap, capacity: int):
        self.path, self._handle, self.mapping, self.capacity = path, handle, mapping, capacity

    @classmethod
    def create(cls, path: str, capacity: int) -> "FrameFile":
        size = DATA_OFFSET + SLOTS * capacity * BYTES_PER_PIXEL
        handle = open(path, "w+b")
        handle.truncate(size)
        mapping = mmap.mmap(handle.fileno(), size)
        FILE_HEADER.pack_into(mapping, 0, MAGIC, VERSION, SLOTS, capacity)
        return cls(path, handle, mapping, capacity)

    @classmethod
    def open(cls, path: str) -> "FrameFile":
        """ValueError where the file is no frame file of this version."""
        handle = open(path, "rb")
        try:
            mapping = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
        except (ValueError, OSError):
            handle.close()
            raise ValueError(f"{path}: empty or unreadable, not a frame file") from None
        magic, version, slots, capacity = FILE_HEADER.unpack_from(mapping, 0)
        if magic != MAGIC or version != VERSION or slots != SLOTS:
            mapping.close()
            handle.close()
            raise ValueError(f"{path}: not a version {VERSION} frame file")
        return cls(path, handle, mapping, capacity)

    def slot_offset(self, slot: int) -> int:
        return DATA_OFFSET + slot * self.capacity * BYTES_PER_PIXEL

    def sequence(self, slot: int) -> int:
        return SLOT_HEADER.unpack_from(self.mapping, SLOT_HEADER_OFFSET + slot * SLOT_HEADER.size)[0]

    def begin_frame(self, slot: int) -> int:
        """Marks ``slot`` as being written (its sequence odd); returns the sequence it will end at."""
        sequence = self.sequence(slot) + 1
        SLOT_HEADER.pack_into(self.mapping, SLOT_HEADER_OFFSET + slot * SLOT_HEADER.size, sequence, -1, 0, 0, 0.0, -1)
        return sequence + 1

    def end_frame(self, slot: int, sequence: int, request_id: int, width: int, height: int, seconds: float,
                  iteration: int) -> None:
        SLOT_HEADER.pack_into(self.mapping, SLOT_HEADER_OFFSET + slot * SLOT_HEADER.size, sequence, request_id,
                              width, height, seconds, iteration)

    def read(self, slot: int, sequence: int) -> Optional[tuple[int, int, bytes, bytes]]:
        """``(width, height, rgba, depth)`` of the frame ``slot`` holds at ``sequence`` (as its
        ``frame`` event named it), copied out; None where the server has written the slot again
        since (the frame is stale: a newer one is on its way)."""
        header_offset = SLOT_HEADER_OFFSET + slot * SLOT_HEADER.size
        found, _, width, height, _, _ = SLOT_HEADER.unpack_from(self.mapping, header_offset)
        if found != sequence or width * height > self.capacity:
            return None
        start = self.slot_offset(slot)
        rgba = self.mapping[start:start + width * height * 16]
        depth = self.mapping[start + width * height * 16:start + width * height * 20]
        if SLOT_HEADER.unpack_from(self.mapping, header_offset)[0] != sequence:
            return None
        return width, height, rgba, depth

    def close(self) -> None:
        self.mapping.close()
        self._handle.close()

    def remove(self) -> None:
        """Closes and deletes the file (the server's, when it outgrows it or stops)."""
        self.close()
        try:
            os.remove(self.path)
        except OSError:
            pass  # Windows keeps a file a reader still maps; the frames folder goes with the parent
