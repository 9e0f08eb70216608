"""matplotlib for pictures written to files, set up once.

Deferred on purpose: importing matplotlib costs about half a second, and only the commands
that draw pictures (report, bench) need it. The Agg backend draws without a display."""

from __future__ import annotations

from types import ModuleType


def pyplot() -> ModuleType:
    """``matplotlib.pyplot`` on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def colormap(name: str):
    """A matplotlib colour map by name (``"inferno"``), without loading pyplot."""
    import matplotlib

    return matplotlib.colormaps[name]
