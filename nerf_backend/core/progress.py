"""Progress on stderr: a tqdm bar on a terminal, a plain line every few seconds elsewhere.

A bar redrawn with carriage returns fills a log file (``RUN.log``, CI output) with thousands of
copies of itself; a log wants a line now and then. Elsewhere the run's own record
(``events.jsonl``, the add-on's panel) carries the progress.

Example::

    bar = Progress(total=300, description="train", unit="it")
    for i in range(300):
        bar.update(1)
        bar.set_postfix(loss="0.01")
    bar.close()
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm

LINE_INTERVAL_S = 10.0  # how often a plain line is written when stderr is not a terminal


class Progress:
    """``enabled=False`` shows nothing; ``terminal`` (default: whether stderr is one) picks
    the bar or the lines. ``seconds=True`` counts seconds of a time budget instead of units."""

    def __init__(self, total: float, description: str, unit: str = "it", initial: float = 0.0,
                 enabled: bool = True, seconds: bool = False, terminal: bool | None = None,
                 stream: TextIO | None = None) -> None:
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.total, self.n, self.description, self.unit, self.seconds = total, min(initial, total), description, unit, seconds
        self.postfix = ""
        self.terminal = enabled and (_is_terminal(self.stream) if terminal is None else terminal)
        self._started = self._last_line = time.monotonic()
        self.bar = None
        if self.terminal:
            # tqdm drops its total once n passes it (then {total:.0f} fails): n never does here.
            self.bar = tqdm(total=total, initial=self.n, desc=description, file=self.stream, unit=unit,
                            dynamic_ncols=True,
                            bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
                            if seconds else None)

    def update(self, amount: float) -> None:
        self.advance_to(self.n + amount)

    def advance_to(self, n: float) -> None:
        """Move to ``n`` (clamped to the total)."""
        n = min(n, self.total)
        if self.bar is not None:
            self.bar.update(n - self.n)
        self.n = n
        if self.enabled and not self.terminal and time.monotonic() - self._last_line >= LINE_INTERVAL_S:
            self._line()

    def set_postfix(self, **values: object) -> None:
        self.postfix = ", ".join(f"{key}={value}" for key, value in values.items())
        if self.bar is not None:
            self.bar.set_postfix(**values)

    def write(self, message: str) -> None:
        """A line of its own (above the bar on a terminal); shown even when progress is off."""
        if self.bar is not None:
            self.bar.write(message, file=self.stream)
        else:
            print(message, file=self.stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        elif self.enabled and not self.terminal:
            self._line()
        self.enabled = False

    def _line(self) -> None:
        self._last_line = time.monotonic()
        elapsed = self._last_line - self._started
        done = f"{self.n:.0f}/{self.total:.0f} s" if self.seconds else f"{self.n:.0f}/{self.total:.0f} {self.unit}"
        postfix = f", {self.postfix}" if self.postfix else ""
        print(f"{self.description}: {done} ({elapsed:.0f} s elapsed{postfix})", file=self.stream, flush=True)


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # a closed or replaced stream
        return False
