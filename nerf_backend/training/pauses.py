"""When the training pauses to validate a view or to write a checkpoint: at a point of its step
cadence (``validate_every``, ``checkpoint_every``), but no more often than lets that kind of
pause take ``pause_share`` of the training time.

Why: ``--max-seconds`` counts the training steps, and the pauses come on top. On lego at
800×800 ``auto`` validated and wrote a checkpoint every 250 steps: its 1 800-second budget took
2 136 s (164 pauses of each kind, at 0.6 s and 1.1-1.6 s), its 600-second one 682 s. Spaced by
their own cost, each kind takes at most ``pause_share`` of the time whatever the machine's step
rate (on a GPU 250 steps are a second or two).

Example:
    >>> pauses = PauseCadence(every=10, share=0.05)
    >>> pauses.due(iteration=10, train_seconds=3.0)
    True
    >>> pauses.took(seconds=0.5, train_seconds=3.0)  # the next waits 0.5 / 0.05 = 10 s of training
    >>> pauses.due(iteration=20, train_seconds=6.0), pauses.due(iteration=130, train_seconds=13.0)
    (False, True)
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PauseCadence:
    every: int  # steps between the points where it may pause
    share: float  # of the training time it may take; 0: at every point
    next_at: float = 0.0  # training seconds before which it waits

    def on_cadence(self, iteration: int) -> bool:
        return iteration % self.every == 0

    def due(self, iteration: int, train_seconds: float) -> bool:
        return self.on_cadence(iteration) and train_seconds >= self.next_at

    def took(self, seconds: float, train_seconds: float) -> None:
        """A pause of ``seconds`` ended at ``train_seconds`` of training."""
        if self.share > 0:
            self.next_at = train_seconds + seconds / self.share
