"""The bench commands' ``--page`` option: their table written as a docs page too. Apart from
``arguments.py``, which every command imports: the bench package is for the bench commands."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..bench.pages import INDEX_NAME, publish_page


def add_page(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--page", type=Path, default=None, metavar="PAGE.md",
                        help="also write the table as a docs page (docs/benchmarks/NAME.md: its name the scene and "
                             "size), with the command and commit, its plot beside it, and that folder's index again")


def publish(args: argparse.Namespace, markdown: Path, plot: Path | None = None) -> None:
    """``--page``'s page of the table ``markdown``, where one was asked for."""
    if args.page is not None:
        page = publish_page(markdown, args.page, plot, getattr(args, "command_line", None))
        print(f"page {page} (index {page.parent / INDEX_NAME})")
