"""``python -m nerf_backend COMMAND ...``: the command line, built from the commands' own modules
(``commands/``, one a command), and how its errors are worded: one line naming the file and the
problem, exit status 2; the traceback only with ``--debug``."""

from __future__ import annotations

import argparse
import shlex
import sys

from .commands import COMMANDS, command_module
from .core.errors import NerfError


class _DefaultsShown(argparse.HelpFormatter):
    """Every option's help ends with its default, unless it says it already or has none."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or not action.option_strings or action.default in (None, False, [], argparse.SUPPRESS):
            return text
        return f"{text} (default: %(default)s)"


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The whole command line, or with ``only`` (a command's name) that command's part alone,
    so that only its module is imported."""
    parser = argparse.ArgumentParser(prog="python -m nerf_backend",
                                     description="Train, render, score and benchmark NeRFs of Blender scenes.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks for errors")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in map(command_module, [only] if only else COMMANDS):
        command_parser = sub.add_parser(command.NAME, help=command.HELP, formatter_class=_DefaultsShown)
        command.add_arguments(command_parser)
        command_parser.set_defaults(run_command=command.run)
    return parser


def _run(args: argparse.Namespace) -> int:
    return args.run_command(args)


def _one_line(exc: NerfError | OSError) -> str:
    if isinstance(exc, NerfError):
        message = str(exc)
    elif exc.filename is not None:  # a full disk, permission denied, a file too large...: "FILE: strerror"
        names = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
        message = f"{names}: {exc.strerror or exc}"
    else:
        message = exc.strerror or str(exc) or type(exc).__name__
    # A name from a dataset may hold a newline: escaped, so the error stays one line.
    return message.replace("\r", "\\r").replace("\n", "\\n")


def _chosen_command(argv: list[str]) -> str | None:
    """The command ``argv`` names (its first word that is not an option), if it is one; else
    None, and the whole command line is built (for its help, or to name the choices)."""
    words = [word for word in argv if not word.startswith("-")]
    return words[0] if words and words[0] in COMMANDS else None


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    """``argv`` read as ``main`` reads it: with the chosen command's part of the command line."""
    return build_parser(_chosen_command(argv)).parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_arguments(argv)
    # Recorded in the bench's tables with the commit, so a figure can be made again.
    args.command_line = shlex.join(["python", "-m", "nerf_backend", *argv])
    try:
        return _run(args)
    except (NerfError, OSError) as exc:
        if args.debug:
            raise
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
