"""The backend's commands, one module each (as nerfstudio's scripts are): each holds its
``NAME``, its ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int`` (the exit status).
``cli.py`` builds the command line from ``COMMANDS``, in this order, and runs the one chosen.
The flags the add-on passes are named in ``nerf_contract.commands``.

A process runs one command, so only that command's module is imported (``command_module``):
importing all of them, with bench's marching cubes and geometry scores, cost every ``train``
about 0.3 s of its start (``docs/testing.md``)."""

from __future__ import annotations

import importlib
from types import ModuleType

# Each command's name on the command line, and the module of this package that holds it.
COMMANDS = {"train": "train", "bench": "bench", "bench-step": "bench_step", "bench-view": "bench_view",
            "bench-kilonerf": "bench_kilonerf", "render": "render", "eval": "evaluate", "compare": "compare",
            "mesh": "mesh", "export": "export", "report": "report", "serve": "serve", "hold-out": "hold_out"}


def command_module(name: str) -> ModuleType:
    """The module of the command called ``name`` (one of ``COMMANDS``), imported now.

    Example:
        >>> command_module("hold-out").NAME
        'hold-out'
    """
    return importlib.import_module(f"{__name__}.{COMMANDS[name]}")
