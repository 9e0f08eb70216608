"""Training pixels drawn where the error is (Instant-NGP's error map).

A scene that leaves much of its frame to the background is learnt there within a few hundred
steps, and uniform sampling goes on spending most rays on it. Here each training image is cut
into ``cells × cells`` tiles that remember the squared error of the last rays drawn in them;
a share of each batch is drawn from tiles in proportion to that error (a uniform pixel within
the tile), the rest uniformly over every pixel, so no pixel is ever left out. The held-out
views are never sampled (this sees only the training images).

Pixel p of a side of n pixels lies in tile ``p · cells // n``: the map holds across the image
pyramid's levels.

Example:
    >>> import torch
    >>> errors = ErrorMap(images=2, cells=4, share=1.0)
    >>> generator = torch.Generator().manual_seed(0)
    >>> for _ in range(20):  # image 1 errs everywhere, image 0 nowhere
    ...     image, pixel = errors.sample(64, 8, 8, generator)
    ...     errors.update(image, pixel, 8, 8, torch.where(image == 1, 1.0, 0.0))
    >>> image, _ = errors.sample(1000, 8, 8, generator)
    >>> float((image == 1).float().mean()) > 0.9  # the erring image is drawn almost alone
    True
"""

from __future__ import annotations

import torch
from torch import Tensor

# A tile's error never counts below this share of the mean (a tile learnt once can still
# regress, and is then seen again).
ERROR_FLOOR = 0.05


class ErrorMap:
    """``sample`` draws (image, row-major pixel) pairs, ``share`` of them from tiles in
    proportion to their remembered error; ``update`` records the error of drawn rays."""

    def __init__(self, images: int, cells: int = 32, share: float = 0.5) -> None:
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"error-map share {share}: a fraction of the batch, in [0, 1]")
        self.cells = cells
        self.share = share
        # Unseen tiles start at the largest error: each is visited before it is judged.
        self.error = torch.ones(images * cells * cells)

    def sample(self, batch: int, height: int, width: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
        """``image [batch]`` and row-major ``pixel [batch]`` in images of ``height × width``."""
        images, cells = self.error.numel() // (self.cells * self.cells), self.cells
        from_error = round(batch * self.share)
        weights = self.error.clamp_min(ERROR_FLOOR * float(self.error.mean()))
        tile = (torch.multinomial(weights, from_error, replacement=True, generator=generator) if from_error
                else torch.zeros(0, dtype=torch.long))
        uniform = batch - from_error
        image = torch.cat([tile // (cells * cells), torch.randint(images, (uniform,), generator=generator)])
        y = torch.cat([_within(tile // cells % cells, cells, height, generator),
                       torch.randint(height, (uniform,), generator=generator)])
        x = torch.cat([_within(tile % cells, cells, width, generator),
                       torch.randint(width, (uniform,), generator=generator)])
        return image, y * width + x

    def update(self, image: Tensor, pixel: Tensor, height: int, width: int, error: Tensor) -> None:
        """Record each drawn ray's ``error [batch]`` (its squared colour error) in its tile: the
        tile keeps the mean of its old value and the rays drawn there now."""
        y, x = pixel // width, pixel % width
        tile = (image * self.cells + y * self.cells // height) * self.cells + x * self.cells // width
        tile, error = tile.cpu(), error.detach().float().cpu()
        total = torch.zeros_like(self.error).index_add_(0, tile, error)
        drawn = torch.zeros_like(self.error).index_add_(0, tile, torch.ones_like(error))
        seen = drawn > 0
        self.error[seen] = 0.5 * self.error[seen] + 0.5 * total[seen] / drawn[seen]


def _within(cell: Tensor, cells: int, side: int, generator: torch.Generator) -> Tensor:
    """A uniform pixel among those of ``side`` whose tile along this axis is ``cell`` (pixel p
    is in tile ``p · cells // side``: ceil(cell · side / cells) up to the next tile's first)."""
    first = (cell * side + cells - 1) // cells
    end = ((cell + 1) * side + cells - 1) // cells
    offset = (torch.rand(cell.shape, generator=generator) * (end - first)).long()
    return (first + offset.clamp_max((end - first - 1).clamp_min(0))).clamp_max(side - 1)
