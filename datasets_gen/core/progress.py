"""Progress over rendered views on stderr: a tqdm bar on a terminal when tqdm is importable,
otherwise a plain line every few seconds (a bar's redraws would fill a log file).

Blender's own Python (e.g. Debian's `blender` binary) usually has no tqdm, and a dataset
render can take hours, so some progress, with the time left, must always be shown.  The total
counts only the views this run renders (a resumed run skips the others), so the estimate is
not skewed by views that take no time.
"""

from __future__ import annotations

import sys
import time
from typing import Any, Optional

LINE_INTERVAL_S = 10.0  # the most often a plain line is written


class ViewProgress:
    """Counts rendered views; use as a context manager and call `advance(split, index)` per view."""

    def __init__(self, total: int, enabled: bool = True, unit: str = "view", desc: str = "rendering") -> None:
        self._total = total
        self._unit = unit
        self._enabled = enabled
        self._done = 0
        self._start = self._last_line = time.monotonic()
        self._bar: Optional[Any] = None
        if enabled and _is_terminal():
            try:
                from tqdm import tqdm
            except ImportError:
                tqdm = None
            if tqdm is not None:
                self._bar = tqdm(total=total, unit=unit, file=sys.stderr, desc=desc)

    def advance(self, split: str, index: int) -> None:
        """Record that view `index` of `split` has been written."""
        self.advance_named(f"{split} r_{index}")

    def advance_named(self, name: str) -> None:
        """Record that the item ``name`` (a view, a frame) has been written."""
        self._done += 1
        if not self._enabled:
            return
        if self._bar is not None:
            self._bar.set_postfix_str(name, refresh=False)
            self._bar.update(1)
        elif self._done == self._total or time.monotonic() - self._last_line >= LINE_INTERVAL_S \
                or self._done == 1:
            self._last_line = time.monotonic()
            elapsed = self._last_line - self._start
            left = elapsed / self._done * (self._total - self._done)
            print(
                f"datasets_gen: {self._done}/{self._total} {self._unit}s ({name}), "
                f"{elapsed:.1f} s, about {_duration(left)} left",
                file=sys.stderr,
                flush=True,
            )

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "ViewProgress":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _is_terminal() -> bool:
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def _duration(seconds: float) -> str:
    """1 h 02 min / 3 min 05 s / 12 s."""
    seconds = int(round(seconds))
    if seconds >= 3600:
        return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"
    if seconds >= 60:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds} s"
