"""A NeRF model: the coarse and fine fields of one config, rendered together."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .config import TrainConfig
from .fields import NerfField
from .ray_rendering import RenderOutput, render_rays


class NerfModel(nn.Module):
    """Coarse field + (optional) fine field; ``forward`` renders rays coarse-to-fine."""

    def __init__(self, config: TrainConfig) -> None:
        super().__init__()
        self.config = config
        self.coarse = NerfField(config.field)
        self.fine = NerfField(config.field) if config.sampling.fine_samples > 0 else None

    def forward(
        self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
        background: Tensor | float = 1.0, generator: torch.Generator | None = None,
    ) -> tuple[RenderOutput, RenderOutput | None]:
        return render_rays(
            self.coarse, self.fine, origins, directions, t_near, t_far,
            self.config.sampling, background, training=self.training, generator=generator,
        )

    @staticmethod
    def final(outputs: tuple[RenderOutput, RenderOutput | None]) -> RenderOutput:
        """The pass whose image is the model's answer: fine if there is one."""
        coarse, fine = outputs
        return fine if fine is not None else coarse
