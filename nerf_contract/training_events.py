"""The training process's events: what ``python -m nerf_backend train`` appends to
``RUN/events.jsonl`` (run_layout.EVENTS_NAME), one JSON object a line, flushed at once, and what
the add-on's panel, the report and the bench read back.

Each kind of event is a dataclass here; its fields are the line's keys, and ``"event"`` names
the kind. Every field has a default, so a log written by an older backend still reads; keys
this version does not know are ignored, and a line cut short by a kill is skipped.

Example:
    >>> line = to_line(Val(iteration=250, psnr=31.2, blank_psnr=9.1, view=0, elapsed_s=12.5, time=1.0))
    >>> line
    '{"event": "val", "iteration": 250, "time": 1.0, "psnr": 31.2, "blank_psnr": 9.1, "view": 0, "elapsed_s": 12.5}'
    >>> events = parse_lines(line + '\\n{"event": "done", "iteration": 300, "reason": "iterations"}\\n{"event": "tr')
    >>> [type(event).__name__ for event in events], events[1].reason
    (['Val', 'Done'], 'iterations')
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Optional, Union


@dataclass(frozen=True)
class TrainingEvent:
    """What every event carries: the iteration it happened at and when (seconds since the epoch)."""

    KIND: ClassVar[str] = ""
    iteration: int = 0
    time: Optional[float] = None


@dataclass(frozen=True)
class Start(TrainingEvent):
    """A training session began (a new run, or a resumed one)."""

    KIND: ClassVar[str] = "start"
    resumed: bool = False
    preset: Optional[str] = None
    device: Optional[str] = None
    cpu_threads: Optional[int] = None
    target_iterations: Optional[int] = None  # None when a time budget ends the training
    max_seconds: Optional[float] = None
    schedule_seconds: Optional[float] = None  # the schedule is laid out over this many seconds


@dataclass(frozen=True)
class Train(TrainingEvent):
    """A training step's figures (every few steps)."""

    KIND: ClassVar[str] = "train"
    loss: Optional[float] = None
    psnr: Optional[float] = None  # of the batch
    lr: Optional[float] = None
    scheduled: Optional[float] = None  # where the schedule stands, 0 to 1
    image_size: Optional[list[int]] = None  # width, height of the images sampled now
    elapsed_s: float = 0.0


@dataclass(frozen=True)
class Val(TrainingEvent):
    """A validation view rendered and scored."""

    KIND: ClassVar[str] = "val"
    psnr: Optional[float] = None
    blank_psnr: Optional[float] = None  # the blank image's, against the same view
    view: Optional[int] = None
    elapsed_s: float = 0.0


@dataclass(frozen=True)
class Checkpoint(TrainingEvent):
    """A checkpoint written."""

    KIND: ClassVar[str] = "checkpoint"
    elapsed_s: float = 0.0
    path: Optional[str] = None


@dataclass(frozen=True)
class Collapse(TrainingEvent):
    """The collapse guard found the model near the blank image, and what it did about it."""

    KIND: ClassVar[str] = "collapse"
    elapsed_s: float = 0.0
    val_psnr: Optional[float] = None
    blank_psnr: Optional[float] = None
    margin_db: Optional[float] = None
    views: Optional[list[int]] = None
    action: str = ""
    reason: str = ""
    final: bool = False


@dataclass(frozen=True)
class Done(TrainingEvent):
    """The session ended; ``reason`` says why (``iterations``, ``time``, ``cancelled``, ``collapsed``...)."""

    KIND: ClassVar[str] = "done"
    elapsed_s: float = 0.0
    reason: Optional[str] = None
    val_psnr: Optional[float] = None


@dataclass(frozen=True)
class Error(TrainingEvent):
    """The session stopped on an error, named in ``message``."""

    KIND: ClassVar[str] = "error"
    message: str = ""


Event = Union[Start, Train, Val, Checkpoint, Collapse, Done, Error]
KINDS: dict[str, type] = {cls.KIND: cls for cls in (Start, Train, Val, Checkpoint, Collapse, Done, Error)}


def to_line(event: TrainingEvent) -> str:
    """The event as one line of JSON (without the newline)."""
    return json.dumps({"event": event.KIND, **dataclasses.asdict(event)})


def from_record(record: Any) -> Optional[Event]:
    """The event a decoded line holds; None for a kind this version does not know."""
    if not isinstance(record, dict) or record.get("event") not in KINDS:
        return None
    cls = KINDS[record["event"]]
    known = {field.name for field in dataclasses.fields(cls)}
    return cls(**{key: value for key, value in record.items() if key in known})


def parse_lines(text: str) -> list[Event]:
    """The events of a log's text, in order; lines that do not decode are skipped."""
    events = []
    for line in text.splitlines():
        try:
            event = from_record(json.loads(line))
        except json.JSONDecodeError:
            continue  # a line cut by a kill mid-write: the rest of the log stands
        if event is not None:
            events.append(event)
    return events


def read_events(path: Path | str) -> list[Event]:
    """The events of the log at ``path`` (``RUN/events.jsonl``); none when it does not exist."""
    path = Path(path)
    if not path.is_file():
        return []
    return parse_lines(path.read_text(encoding="utf-8", errors="replace"))
