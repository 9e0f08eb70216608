"""The error heatmap that the report and ``compare`` both draw: mean absolute RGB error per
pixel on one fixed scale, so that views and runs compare. Below both, so neither imports
the other."""

from __future__ import annotations

import numpy as np

from ..core.plotting import colormap

# 0 (black) to ERROR_SCALE (white-yellow) and above.
ERROR_SCALE = 0.25
ERROR_COLOURMAP = "inferno"


def error_heatmap(rendered: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """RGB in [0, 1] of ``|rendered - reference|`` averaged over channels, through the colour map."""
    error = np.abs(rendered - reference).mean(axis=-1)
    return colormap(ERROR_COLOURMAP)(np.clip(error / ERROR_SCALE, 0.0, 1.0))[..., :3]
