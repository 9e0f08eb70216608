"""Training's progress bar: over iterations, or over training seconds when a time budget will
end the run first (then the time left is the real one)."""

from __future__ import annotations

from ..core.progress import Progress


class TrainingProgress:
    def __init__(self, iterations: int, iteration: int, max_seconds: float | None, seconds: float,
                 enabled: bool, description: str) -> None:
        self.by_time = max_seconds is not None
        total, initial = (max_seconds, seconds) if self.by_time else (iterations, iteration)
        self.bar = Progress(total, description, unit="s" if self.by_time else "it", initial=initial,
                            enabled=enabled, seconds=self.by_time)
        self.iteration = iteration

    def step(self, iteration: int, seconds: float) -> None:
        self.bar.advance_to(seconds if self.by_time else iteration)
        self.iteration = iteration

    def show(self, **values: str) -> None:
        self.bar.set_postfix(it=self.iteration, **values) if self.by_time else self.bar.set_postfix(**values)

    def note(self, message: str) -> None:
        """A line above the bar (or alone on stderr when the bar is off): events the user must see."""
        self.bar.write(message)

    def close(self) -> None:
        self.bar.close()
