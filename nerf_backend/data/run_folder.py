"""A run folder: its config, its event log, its checkpoint and the lock that keeps two
trainings out of the same folder.

The folder's names are the contract's (``nerf_contract.run_layout``, which the add-on reads
too), and so are its events (``nerf_contract.training_events``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import pickle
import shutil
import threading
import time
from pathlib import Path
from typing import Iterator

import torch

from nerf_contract.run_layout import CHECKPOINT_NAME, CONFIG_NAME, EVENTS_NAME, RENDERS_DIR
from nerf_contract.training_events import Event, TrainingEvent, read_events, to_line

from ..core.errors import RunError
from ..core.files import atomic_write, remove_stale_temporaries, write_json


def _first_line(error: Exception) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


def serialised(state: dict) -> io.BytesIO:
    """A checkpoint's state as the bytes ``torch.save`` writes, in memory: a snapshot the
    training may change behind, and a write failure (a full disk) is then the OS's error, not
    one of torch's."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer


LOCK_NAME = ".lock"
IN_USE = "another training is already using this run folder"


class RunFolder:
    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self._lock_handle = None
        self._log_lock = threading.Lock()

    @property
    def config_path(self) -> Path:
        return self.path / CONFIG_NAME

    @property
    def events_path(self) -> Path:
        return self.path / EVENTS_NAME

    @property
    def checkpoint_path(self) -> Path:
        return self.path / CHECKPOINT_NAME

    def renders_dir(self, split: str) -> Path:
        return self.path / RENDERS_DIR / split

    def read_config(self) -> dict:
        if not self.config_path.is_file():
            raise RunError(f"{self.path}: not a run folder (no {CONFIG_NAME}); train one first")
        try:
            return json.loads(self.config_path.read_text())
        except json.JSONDecodeError as exc:
            raise RunError(f"{self.config_path}: not valid JSON ({exc})") from None

    def write_config(self, config: dict) -> None:
        write_json(self.config_path, config)

    def log(self, event: TrainingEvent) -> None:
        """Append one event line, stamped with the time; flushed at once so a reader (the
        add-on) sees it live. Safe from several threads (a checkpoint's event is logged by
        the thread that wrote it)."""
        with self._log_lock:
            line = to_line(dataclasses.replace(event, time=time.time()))
            try:
                with open(self.events_path, "a", encoding="utf-8") as handle:
                    handle.write(line + "\n")
                    handle.flush()
            except OSError as exc:
                raise RunError(f"{self.events_path}: cannot write ({exc.strerror or exc})") from exc

    def read_events(self) -> list[Event]:
        return read_events(self.events_path)

    def save_checkpoint(self, state: dict) -> None:
        self.write_checkpoint(serialised(state))

    def write_checkpoint(self, buffer: io.BytesIO) -> None:
        """``serialised``'s bytes as the checkpoint, replacing it whole or not at all."""
        atomic_write(self.checkpoint_path, lambda tmp: tmp.write_bytes(buffer.getbuffer()))

    def load_checkpoint(self, device: torch.device, mapped: bool = False) -> dict:
        """The checkpoint's data: tensors, numbers, strings, lists and dicts only
        (``weights_only=True``), so that opening a run folder someone else made cannot run
        code. A file holding anything else is refused with a one-line error.

        ``mapped``: the file memory-mapped, its tensors read only where they are used; for
        reading a checkpoint, not for resuming from it (the optimiser's state, half of lego's
        278 MB thirty-minute checkpoint, is then never read: loading it 224-433 → 14-18 ms, the
        model's tensors read through the map in 8-11 ms)."""
        if not self.checkpoint_path.is_file():
            raise RunError(f"{self.checkpoint_path}: no checkpoint to load")
        try:
            return torch.load(self.checkpoint_path, map_location=device, weights_only=True, mmap=mapped)
        except pickle.UnpicklingError:
            raise RunError(f"{self.checkpoint_path}: refused: it holds Python objects, not only tensors and plain "
                           f"data, and loading them could run code (this project's checkpoints hold data only)") from None
        except Exception as exc:  # torch raises several types for damaged files
            raise RunError(f"{self.checkpoint_path}: cannot read checkpoint ({_first_line(exc)})") from None

    def existing_files(self) -> list[Path]:
        """What the folder holds besides its lock."""
        return [p for p in self.path.iterdir() if p.name != LOCK_NAME] if self.path.is_dir() else []

    def refuse_to_replace(self, resume: bool, overwrite: bool, holding_lock: bool = False) -> None:
        """A non-empty folder is reused only when resuming or told to overwrite."""
        if not resume and not overwrite and self.existing_files():
            if not holding_lock and self.in_use():  # the probe would see our own lock
                raise RunError(f"{self.path}: {IN_USE}")
            raise RunError(f"{self.path}: run folder exists and is not empty; pass --resume to continue it or "
                           f"--overwrite to replace it")

    @contextlib.contextmanager
    def claimed(self, resume: bool, overwrite: bool) -> Iterator["RunFolder"]:
        """The folder locked for one training: checked again under the lock, emptied for a new
        run (a resumed one must hold a run's config), released on leaving."""
        self.acquire_lock()
        try:
            self.refuse_to_replace(resume, overwrite, holding_lock=True)
            if resume:
                self.read_config()  # raises a clear error if this is not a run
            else:
                for path in self.existing_files():
                    shutil.rmtree(path) if path.is_dir() else path.unlink()
            yield self
        finally:
            self.release_lock()

    def acquire_lock(self) -> None:
        """Hold an exclusive OS lock on RUN/.lock for the life of this process; a second
        trainer on the same folder gets a clear error. The OS drops it even on kill -9."""
        self.path.mkdir(parents=True, exist_ok=True)
        lock = self.path / LOCK_NAME
        while True:
            handle = open(lock, "a+")
            try:
                _lock_file(handle)
            except OSError:
                handle.close()
                raise RunError(f"{self.path}: {IN_USE}") from None
            # A trainer that just finished removes its lock file: if ours was that file, the
            # lock we hold is on a name nobody sees any more; take the new one instead.
            if lock.is_file() and os.path.samestat(os.fstat(handle.fileno()), os.stat(lock)):
                break
            handle.close()
        handle.seek(0)
        handle.truncate()
        handle.write(str(os.getpid()))
        handle.flush()
        self._lock_handle = handle
        remove_stale_temporaries(self.path)  # a killed trainer's half-written checkpoint

    def in_use(self) -> bool:
        """True while another process holds this folder's lock (creates nothing)."""
        lock = self.path / LOCK_NAME
        if not lock.is_file():
            return False
        with open(lock, "r+") as handle:
            try:
                _lock_file(handle)
            except OSError:
                return True
        return False  # closing the handle released the probe's lock

    def release_lock(self) -> None:
        """Drop the lock and remove RUN/.lock (still holding it, so no one else's is removed)."""
        if self._lock_handle is not None:
            try:
                (self.path / LOCK_NAME).unlink()
            except OSError:  # Windows will not remove an open file; the lock still goes
                pass
            self._lock_handle.close()
            self._lock_handle = None


def _lock_file(handle) -> None:
    try:
        import fcntl
    except ImportError:  # Windows
        import msvcrt

        handle.seek(0)
        msvcrt.locking(handle.fileno(), msvcrt.LK_NBLCK, 1)
        return
    fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
