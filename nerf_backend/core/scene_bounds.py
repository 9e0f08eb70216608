"""The scene's axis-aligned box: the one geometric fact that datasets, ray bounds, fields
and presets all share, so it lives below all of them."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SceneBounds:
    """Axis-aligned box holding the scene's renderable geometry, in the dataset's frame."""

    box_min: tuple[float, float, float]
    box_max: tuple[float, float, float]

    def padded(self, fraction: float) -> "SceneBounds":
        """The box grown on every side by ``fraction`` of its largest extent (geometry
        touches the bounds; a field needs a little room around it)."""
        size = max(hi - lo for lo, hi in zip(self.box_min, self.box_max))
        pad = fraction * size
        return SceneBounds(
            tuple(v - pad for v in self.box_min), tuple(v + pad for v in self.box_max)  # type: ignore[arg-type]
        )


def vertices_for(resolution: int, extent: tuple[float, float, float]) -> tuple[int, int, int]:
    """Vertices on each axis of a box of ``extent`` with ``resolution`` along its longest
    side and cells as close to cubes as whole numbers allow.

    Example:
        >>> vertices_for(65, (2.0, 2.0, 0.5))
        (65, 65, 17)
    """
    cell = max(extent) / (resolution - 1)
    return tuple(max(2, round(side / cell) + 1) for side in extent)  # type: ignore[return-value]
