"""The model contract: what the trainer, the renderer and the bench may ask of any model.

A model renders a batch of rays: ``forward(origins, directions, t_near, t_far, background,
generator) -> list[RenderOutput]``; the training loss sums the squared error of every output
(the paper's coarse + fine) and the last output is the image (``final_output``). A model
declares its optimiser's parameter groups, keeps its own state between steps
(``before_step``) and takes the shapes of a checkpoint it is loaded from (``match_state``).
Its own settings are groups it names in ``SETTINGS``; a run's config carries every registered
model's groups, so a new model's settings need no change outside the model.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator, Protocol

import torch
from torch import Tensor, nn

from ..core.scene_bounds import SceneBounds
from ..data.occupancy_prior import OccupancyPrior
from ..model_components.render_output import RenderOutput


class ModelSettings(Protocol):
    """The settings models read (the run's ``TrainConfig`` has them, among training ones):
    these, and each group a model names in its ``SETTINGS`` as an attribute of that name."""

    model: str
    grid_step_ratio: float
    occupancy_warmup: int
    occupancy_every: int
    occupancy_alpha_threshold: float
    render_alpha_threshold: float
    fit_box_at: int
    refraction: bool


@dataclass(frozen=True)
class ParameterGroup:
    """Parameters the optimiser treats alike; ``learning_rate`` names the setting that gives
    their rate (``"learning_rate"`` or ``"network_learning_rate"``)."""

    name: str
    parameters: list[nn.Parameter]
    learning_rate: str


class Model(nn.Module):
    """Base of every model; subclasses implement ``forward`` and ``build``."""

    # Rays per forward pass when rendering whole images, unless the caller names its own.
    # Measured on 2 CPU cores (preview preset, 100×100 view): 1024 rays took 1.7 s a view,
    # 4096 took 2.6 s, 8192 took 3.1 s (larger activations cost page faults).
    render_chunk: int = 1024
    # Whether the model reads the dataset's occupancy prior (where the scene can be).
    uses_occupancy_prior: bool = False
    # The groups of settings the model reads, by name (``"grid"``: ``GridFieldConfig``): the
    # run's config has one of each, with the class's defaults unless a preset or --set says.
    SETTINGS: dict[str, type] = {}

    @classmethod
    def build(cls, settings: ModelSettings, box: SceneBounds | None, prior: OccupancyPrior | None) -> "Model":
        """A new model for ``settings`` over the scene's ``box`` (None: no box known)."""
        raise NotImplementedError

    def forward(
        self, origins: Tensor, directions: Tensor, t_near: Tensor, t_far: Tensor,
        background: Tensor | float = 1.0, generator: torch.Generator | None = None,
    ) -> list[RenderOutput]:
        raise NotImplementedError

    def density_at(self, points: Tensor) -> Tensor:
        """Density ``[P]`` at world points ``[P, 3]``: the geometry the image is rendered from
        (meshes are extracted from it)."""
        raise NotImplementedError

    def colour_at(self, points: Tensor, directions: Tensor) -> Tensor:
        """Colour ``[P, 3]`` at ``points`` seen along ``directions``."""
        raise NotImplementedError

    def surface_function(self) -> Callable[[Tensor], Tensor] | None:
        """A function of world points ``[P, 3] -> [P]``, positive inside and zero on the surface
        (a signed distance's negative), whose zero level set is the model's mesh; None for a
        model whose surface is a level of its density."""
        return None

    def regularisation(self, generator: torch.Generator | None = None) -> Tensor | None:
        """Loss terms of the model's own added to the photometric loss at each training step
        (the surface field's eikonal term), or None."""
        return None

    def parameter_groups(self) -> list[ParameterGroup]:
        """The optimiser's groups, in a fixed order (checkpoints store the optimiser by it)."""
        return [ParameterGroup("networks", list(self.parameters()), "learning_rate")]

    def before_step(self, iteration: int, scheduled: int, steps_left: float | None = None) -> bool:
        """Called before each training step: ``iteration`` counts the steps taken (what
        per-step upkeep follows), ``scheduled`` is the run's place in its preset's schedule,
        in that schedule's steps (what growth follows; under a time budget it is the share
        of the budget spent, so the schedule ends with the budget), ``steps_left`` the steps
        the budget still allows at the run's rate so far (None without a budget). True when
        the parameters were replaced (the optimiser must be rebuilt)."""
        return False

    def after_step(self) -> None:
        """Called after each optimiser step: projections of the model's parameters back onto
        the constraints it keeps (the surface field's bounds from Blender's prior)."""

    def take_note(self) -> str | None:
        """What the model's schedule decided that the user should hear (once), or None."""
        return None

    def coarse_detail(self) -> float | None:
        """The finest detail (world units) the model holds now while it is still growing
        toward finer detail on its schedule; None when it holds its final detail (or has no
        such schedule): the trainer then samples rays from the full-size images."""
        return None

    @contextmanager
    def march_step_scaled(self, scale: float) -> Iterator[None]:
        """Inside the block, render with a march step ``scale`` times the model's own: fewer
        samples a ray for a coarser sum (the live view's draft frames). A model that does not
        march a fixed step (the NeRF MLP's stratified samples) renders as it always does."""
        yield

    def content_corners(self) -> Tensor | None:
        """The eight corners ``[N, 8, 3]`` (the model's frame) of boxes outside which rendering
        finds nothing: a ray that meets none of them renders as the background. None where the
        model does not know (every ray is rendered)."""
        return None

    def match_state(self, state: dict[str, Tensor]) -> None:
        """Take the shapes the checkpoint ``state`` was saved with, so its tensors load."""

    def restore(self, state: dict[str, Tensor]) -> None:
        """Load a checkpoint's weights, at the shapes they were saved with (a grid upsampled
        since the model was built): what both resuming and rendering do."""
        self.match_state(state)
        self.load_state_dict(state)


def final_output(outputs: list[RenderOutput]) -> RenderOutput:
    """The output whose image is the model's answer (the paper's fine pass)."""
    return outputs[-1]
