"""Where a surface can lie, from Blender's occupancy prior: bounds on the signed distance.

``datasets_gen`` marks every prior cell within one cell of a sample of a renderable triangle
(samples lie within a cell of every point of it), then grows the marks by the margin
(``margin_cells``, a cube on each side) into the ``surface`` cells; ``solid`` adds what they
enclose. So the true surface lies in the *band*: the surface cells less a margin's layer on
each side. Every cell the exterior (not solid) reaches by the margin, and every cell the
interior (solid, not surface) reaches, holds no surface. From that:

* at a point of the exterior side, the signed distance is at least the distance to the band
  (it is outside every object, and the nearest surface lies in the band);
* at a point of the interior side, it is at most minus the distance to the band.

``band_distances`` gives both distances at the prior's cell centres (in cells, 0 in the
band); ``SignedDistanceBounds`` reads them anywhere as lower and upper bounds. On the three
real scenes' 800×800 priors (A.blend, RobotExpressive, 20_specular; 2 million points of each
scene's own triangles, a scratch check) the triangles never leave the bounds, and points near
them keep at least half a cell of slack. ``tests/test_occupancy_prior.py`` checks Blender's own
ray hits on real scenes, ``tests/test_surface_band.py`` a voxelised sphere against its exact
distance.

Example (a plane's cells grown by two on each side, as a margin of one marks them, in a box
of 9 cells):
    >>> import numpy as np
    >>> shell = np.zeros((9, 3, 3), bool); shell[2:7] = True  # the plane at x = 4, grown by 2
    >>> outside, inside = band_distances(shell, shell, margin_cells=1)
    >>> outside[:, 1, 1].tolist()  # cells 3-5 are the band
    [3.0, 2.0, 1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0]
    >>> float(inside.max())  # a plane encloses nothing
    0.0
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .distance_transform import distance_to_unset

_CUBE = np.ones((3, 3, 3), bool)  # the prior's dilation: a cube of a cell on each side


def band_distances(surface: np.ndarray, solid: np.ndarray, margin_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """``(outside, inside)`` ``[nx, ny, nz]`` float32: at each prior cell, the distance (in
    cells, between cell centres) to the nearest band cell from the exterior side and from the
    interior side; 0 in the band and on the other side."""
    exterior = ~solid
    interior = solid & ~surface
    if margin_cells > 0:
        from scipy import ndimage  # here: scipy.ndimage takes 0.3 s to import, and only surfaces need it
        exterior = ndimage.binary_dilation(exterior, _CUBE, iterations=margin_cells)
        interior = ndimage.binary_dilation(interior, _CUBE, iterations=margin_cells) & ~exterior
    return distance_to_unset(exterior), distance_to_unset(interior)


class SignedDistanceBounds(nn.Module):
    """``forward(x [P, 3]) -> (lower [P], upper [P])``: bounds on the true signed distance
    (world units, negative inside) at world points; ``-inf`` / ``inf`` where nothing is known
    (in the band, and on the side it is not). Beyond the prior's box (empty, like its border
    cells) a point keeps its nearest border cell's distance: less than its own.

    Example (the plane above, in a box of side 0.9 from the origin):
        >>> import numpy as np
        >>> shell = np.zeros((9, 3, 3), bool); shell[2:7] = True
        >>> bounds = SignedDistanceBounds(shell, shell, (0.0, 0.0, 0.0), 0.1, margin_cells=1)
        >>> lower, upper = bounds(torch.tensor([[0.05, 0.15, 0.15], [0.45, 0.15, 0.15]]))
        >>> [round(v, 3) for v in lower.tolist()], upper.tolist()
        ([0.3, -inf], [inf, inf])
    """

    def __init__(self, surface: np.ndarray, solid: np.ndarray, box_min: tuple[float, float, float],
                 cell_size: float, margin_cells: int) -> None:
        super().__init__()
        outside, inside = band_distances(surface, solid, margin_cells)
        volume = np.stack([outside, inside]).astype(np.float32) * cell_size
        # [1, 2, nz, ny, nx], as grid_sample reads it; rebuilt from the prior, never saved.
        self.register_buffer("distances", torch.from_numpy(volume).permute(0, 3, 2, 1)[None].contiguous(),
                             persistent=False)
        shape = np.array(surface.shape, dtype=np.float64)
        self.register_buffer("first_centre", torch.tensor(np.asarray(box_min) + cell_size / 2, dtype=torch.float32),
                             persistent=False)
        self.register_buffer("centre_span", torch.tensor(cell_size * (shape - 1), dtype=torch.float32),
                             persistent=False)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        normalised = (x.float() - self.first_centre) / self.centre_span * 2 - 1
        distance = F.grid_sample(self.distances, normalised.view(1, -1, 1, 1, 3), mode="bilinear",
                                 padding_mode="border", align_corners=True).view(2, -1)
        # Between a band cell (0) and its neighbour the distance rises from 0: the bound holds
        # at once (a point just off the band is at least on the right side of the surface).
        lower = torch.where(distance[0] > 0, distance[0], -torch.inf)
        upper = torch.where(distance[1] > 0, -distance[1], torch.inf)
        return lower, upper
