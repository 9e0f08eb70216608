"""Undoable changes to the user's Blender data, so rendering leaves the open scene as it was.

The add-on renders the scene the user has open; the generator must force render settings,
colour management, film, view layers, visibility and add a camera, and afterwards every one of
those changes must be gone.  Each change goes through a `SettingsJournal`, which remembers the
previous value (or the datablock it created) and restores everything in reverse order.
"""

from __future__ import annotations

import sys
from typing import Any, Callable, Iterable

import bpy

_SCALAR_TYPES = {"BOOLEAN", "INT", "FLOAT", "STRING", "ENUM"}


def _copy(value: Any) -> Any:
    """A detached copy of an RNA value (arrays and vectors are live views otherwise)."""
    if isinstance(value, (bool, int, float, str, type(None), set)):
        return value
    try:
        return tuple(value)
    except TypeError:
        return value


class SettingsJournal:
    """Set RNA properties and create datablocks, remembering how to undo each step."""

    def __init__(self) -> None:
        self._undo: list[tuple[str, Callable[[], None]]] = []

    def set(self, owner: Any, attribute: str, value: Any) -> None:
        """setattr, remembering the old value (no entry when the value is already right)."""
        old = _copy(getattr(owner, attribute))
        if old == _copy(value):
            return
        setattr(owner, attribute, value)
        self._undo.append((f"{owner!r}.{attribute}", lambda: setattr(owner, attribute, old)))

    def set_if_present(self, owner: Any, attribute: str, value: Any) -> bool:
        """`set` for properties only some Blender versions have; return whether it existed."""
        if not hasattr(owner, attribute):
            return False
        self.set(owner, attribute, value)
        return True

    def on_restore(self, description: str, undo: Callable[[], None]) -> None:
        """Register an arbitrary undo step (e.g. removing a datablock this run created)."""
        self._undo.append((description, undo))

    def snapshot(self, owner: Any, first: Iterable[str] = ()) -> None:
        """Remember every writable scalar property of `owner`, restored together (`first` first).

        For structs whose properties constrain each other (image format settings: the file
        format decides which colour depths exist), where restoring one at a time can fail.
        """
        values = {}
        for prop in owner.bl_rna.properties:
            if prop.identifier == "rna_type" or prop.is_readonly or prop.type not in _SCALAR_TYPES:
                continue
            values[prop.identifier] = _copy(getattr(owner, prop.identifier))
        order = [name for name in first if name in values] + [name for name in values if name not in first]

        def restore() -> None:
            for name in order:
                try:
                    if _copy(getattr(owner, name)) != values[name]:
                        setattr(owner, name, values[name])
                except (AttributeError, TypeError, ValueError):
                    pass  # a value this state of the struct does not accept (e.g. enum filtered)

        self._undo.append((f"{owner!r} (all settings)", restore))

    def restore(self) -> None:
        """Undo every change, newest first; a step that fails is reported and skipped."""
        while self._undo:
            description, undo = self._undo.pop()
            try:
                undo()
            except (AttributeError, TypeError, ValueError, ReferenceError, RuntimeError) as error:
                print(f"datasets_gen: warning: could not restore {description}: {error}", file=sys.stderr)


def remove_datablock(collection: "bpy.types.bpy_prop_collection", block: "bpy.types.ID") -> Callable[[], None]:
    """An undo step that deletes a datablock this run created (if it still exists)."""
    name = block.name

    def remove() -> None:
        existing = collection.get(name)
        if existing is not None:
            collection.remove(existing)

    return remove
