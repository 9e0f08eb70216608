"""Caches derived from tensors: their key and the one way they are kept, for every such cache.

Example:
    >>> import torch
    >>> weight = torch.zeros(3)
    >>> before = values_key([weight])
    >>> _ = weight.add_(1)  # an in-place update (an optimiser step) bumps the version
    >>> values_key([weight]) == before
    False
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Iterable
from typing import TypeVar

from torch import Tensor

Derived = TypeVar("Derived")


def values_key(tensors: Iterable[Tensor]) -> tuple:
    """What identifies the values the tensors hold: their storage, device, in-place version,
    type and shape. A cache keyed on it is rebuilt when a tensor is updated in place, resized,
    replaced or moved to another device (``module.to`` keeps a parameter's identity and
    swaps its storage, so ``id`` alone would keep a cache of the old device)."""
    return tuple((t.data_ptr(), t.device, t._version, t.dtype, t.shape) for t in tensors)


def kept_derived(owner: object, name: str, tensors: Iterable[Tensor], build: Callable[[], Derived],
                 extra: Hashable = None) -> Derived:
    """``build()``, kept on ``owner`` under ``name`` until the values of ``tensors``
    (``values_key``) or ``extra`` change. Held in the owner's ``__dict__``: on a module it is
    no parameter, buffer or part of the checkpoint.

    Example:
        >>> import torch
        >>> class Owner:
        ...     weight = torch.ones(2)
        >>> owner, builds = Owner(), []
        >>> def doubled():
        ...     builds.append(1)
        ...     return owner.weight * 2
        >>> for _ in range(3):
        ...     kept = kept_derived(owner, "doubled", [owner.weight], doubled)
        >>> _ = owner.weight.add_(1)
        >>> kept_derived(owner, "doubled", [owner.weight], doubled).tolist(), len(builds)
        ([4.0, 4.0], 2)
    """
    key = (values_key(tensors), extra)
    kept = owner.__dict__.setdefault("_kept_derived", {})
    if name not in kept or kept[name][0] != key:
        kept[name] = (key, build())
    return kept[name][1]
