"""The world's light as a learned function of direction: what a ray sees where it leaves the
scene after glass has bent or reflected it (``model_components.glass``)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .spherical_harmonics import C0, sh_basis, sh_count

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

    def start_at(self, colour: tuple[float, float, float]) -> None:
        """Start as one uniform ``colour`` in every direction (the world Blender says the scene
        has, as a pixel shows it), learned on from there. Started grey instead, a glass dish on a
        uniform world at 100×100 learned its world seen below it as 0.68 in 120 s where the
        images show 0.86: only the rays bent through the glass teach it.

        Example:
            >>> environment = Environment()
            >>> environment.start_at((0.863, 0.2, 0.5))
            >>> [round(v, 3) for v in environment(torch.tensor([[0.0, 0.6, -0.8]]))[0].tolist()]
            [0.863, 0.2, 0.5]
        """
        light = torch.tensor(colour, dtype=self.harmonics.dtype).clamp(0.01, 0.99)
        with torch.no_grad():
            self.harmonics.zero_()
            self.harmonics[0] = torch.logit(light) / C0

    def forward(self, directions: Tensor) -> Tensor:
        return torch.sigmoid(sh_basis(directions.to(self.harmonics.dtype), ENVIRONMENT_DEGREE) @ self.harmonics)
