"""What one call of ``train`` did: where it stopped, why, and how fast it trained."""

from __future__ import annotations

from dataclasses import dataclass

from .collapse_guard import Verdict


@dataclass
class TrainSummary:
    iteration: int
    train_seconds: float
    stop_reason: str  # "iterations", "time", "cancelled" or "collapsed"
    val_psnr: float | None
    collapse: Verdict | None = None  # the guard's last verdict when the run ended collapsed
    started_at: int = 0  # the iteration this call began at (a resumed run's checkpoint)
    # Throughput over the run's training time: rays, and samples the field was evaluated at
    # with gradients (None: a checkpoint written before they were counted).
    rays_per_second: float | None = None
    samples_per_second: float | None = None

    def throughput_words(self) -> str:
        """``rays_per_second`` and ``samples_per_second`` for people ("" when not counted).

        Example:
            >>> summary = TrainSummary(10, 2.0, "time", None, rays_per_second=20480.0, samples_per_second=3.1e5)
            >>> summary.throughput_words()
            '20 480 rays and 0.31 M samples a second'
        """
        if self.rays_per_second is None or self.samples_per_second is None:
            return ""
        return f"{self.rays_per_second:,.0f} rays and {self.samples_per_second / 1e6:.2f} M samples a second".replace(
            ",", " ")

    @property
    def had_nothing_to_do(self) -> bool:
        """A resumed run that was already at its iteration count or time budget."""
        return self.started_at == self.iteration and self.stop_reason in ("iterations", "time")
