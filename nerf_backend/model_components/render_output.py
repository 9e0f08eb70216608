"""What rendering a batch of rays returns, whatever the model."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass
class RenderOutput:
    """What one pass renders for each ray."""

    rgb: Tensor  # [R, 3], composited over the background
    depth: Tensor  # [R], expected distance along the ray (0 where empty)
    opacity: Tensor  # [R], 1 - final transmittance
    # Per-sample detail for training; None from renders that stop rays early (inference).
    weights: Tensor | None  # [R, S]
    t_edges: Tensor | None  # [R, S+1]
    # The samples the field was evaluated at with gradients, where fewer than every one of
    # ``weights`` (a march that skips empty and hidden space); None: all of them.
    field_samples: int | None = None
