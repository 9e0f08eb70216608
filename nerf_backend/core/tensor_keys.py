"""The key of a cache derived from tensors, one definition for every such cache.

Example:
    >>> import torch
    >>> weight = torch.zeros(3)
    >>> before = values_key([weight])
    >>> _ = weight.add_(1)  # an in-place update (an optimiser step) bumps the version
    >>> values_key([weight]) == before
    False
"""

from __future__ import annotations

from collections.abc import Iterable

from torch import Tensor


def values_key(tensors: Iterable[Tensor]) -> tuple:
    """What identifies the values the tensors hold: their storage, device, in-place version,
    type and shape. A cache keyed on it is rebuilt when a tensor is updated in place, resized,
    replaced or moved to another device (``module.to`` keeps a parameter's identity and
    swaps its storage, so ``id`` alone would keep a cache of the old device)."""
    return tuple((t.data_ptr(), t.device, t._version, t.dtype, t.shape) for t in tensors)
