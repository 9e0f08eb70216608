"""The backend's commands, one module each (as nerfstudio's scripts are): each holds its
``NAME``, its ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int`` (the exit status).
``cli.py`` builds the command line from ``COMMANDS``, in this order, and runs the one chosen.
The flags the add-on passes are named in ``nerf_contract.commands``."""

from . import (bench, bench_kilonerf, bench_step, bench_view, compare, evaluate, export, hold_out, mesh, render, report,
               serve, train)

COMMANDS = (train, bench, bench_step, bench_view, bench_kilonerf, render, evaluate, compare, mesh, export, report, serve,
            hold_out)
