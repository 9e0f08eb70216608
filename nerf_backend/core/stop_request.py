"""SIGINT/SIGTERM as a flag a loop checks between steps, so a step always finishes (and the
loop can save) before it stops."""

from __future__ import annotations

import signal
import threading


class StopRequest:
    """``with StopRequest() as stop:`` … ``if stop.requested: …``; the signals' handlers are
    restored on leaving (off the main thread, where handlers cannot be set, it never fires)."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: dict[int, object] = {}

    def __enter__(self) -> "StopRequest":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        self.requested = True

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
