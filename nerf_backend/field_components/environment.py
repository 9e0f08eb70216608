"""The world's light as a learned function of direction: what a ray sees where it leaves the
scene after glass has bent or reflected it (``model_components.glass``)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .spherical_harmonics import sh_basis, sh_count

# The world's light seen through glass, as spherical harmonics of the direction (degree 2: a
# uniform world, or one brighter above than below).
ENVIRONMENT_DEGREE = 2


class Environment(nn.Module):
    """What a ray bent by the glass (or reflected by it) sees where it leaves the scene: the
    world's light, learned, a colour a direction (``sigmoid`` of spherical harmonics). The
    camera's own rays see the images' background instead: with a transparent film Cycles leaves
    the world out of the pixels it shows directly, but not of those it shows through glass
    (glass_over_checker's ball is opaque, the world's colour, where the rays through it go up).

    Example:
        >>> environment = Environment()
        >>> environment(torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])).tolist()  # grey until trained
        [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]
    """

    def __init__(self) -> None:
        super().__init__()
        self.harmonics = nn.Parameter(torch.zeros((sh_count(ENVIRONMENT_DEGREE), 3)))

    def forward(self, directions: Tensor) -> Tensor:
        return torch.sigmoid(sh_basis(directions.to(self.harmonics.dtype), ENVIRONMENT_DEGREE) @ self.harmonics)
