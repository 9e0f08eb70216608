"""The benchmark pages of ``docs/benchmarks/`` and their index: a bench command given
``--page PATH`` writes its table there as a page (its plot beside it) and the folder's index
(``README.md``) again, so the figures the guides quote stay with the command and commit that
made them.

Example:
    >>> page_provenance("Made by `python -m nerf_backend bench D --out B` at commit 1a2b3c4+changes.")
    ('python -m nerf_backend bench D --out B', '1a2b3c4+changes')
    >>> page_summary("# bench-step: auto on A\\n\\n800×800 images, 100 train views.")
    'bench-step: auto on A'
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from ..core.errors import NerfError
from ..core.provenance import provenance, provenance_line

INDEX_NAME = "README.md"
_COMMAND = re.compile(r"`(python -m nerf_backend [^`]+)`")
_COMMIT = re.compile(r"at commit ([0-9a-f]{7,40}(?:\+changes)?)")
SUMMARY_CHARACTERS = 160


def page_provenance(text: str) -> tuple[str | None, str | None]:
    """The command and the commit a page says made it (None for what it does not say)."""
    command, commit = _COMMAND.search(text), _COMMIT.search(text)
    return (" ".join(command.group(1).split()) if command else None), (commit.group(1) if commit else None)


def page_summary(text: str) -> str:
    """A page's heading, else its first sentence (shortened to SUMMARY_CHARACTERS)."""
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("#"):
            return line.lstrip("# ").strip()
        if line and not line.startswith(("|", "!", "<")):
            sentence = re.split(r"(?<=\.)\s", line, maxsplit=1)[0]
            return sentence if len(sentence) <= SUMMARY_CHARACTERS else sentence[:SUMMARY_CHARACTERS - 1] + "…"
    return ""


def index_markdown(folder: Path) -> str:
    """The index of the pages in ``folder``: each linked, with what it opens with and the
    command and commit that made it."""
    rows = []
    for page in sorted(p for p in folder.glob("*.md") if p.name != INDEX_NAME):
        text = page.read_text(encoding="utf-8")
        command, commit = page_provenance(text)
        made = f"`{command}`" if command else "not recorded on the page"
        rows.append(f"| [{page.stem}]({page.name}) | {page_summary(text).replace('|', '/')} | {made} | "
                    f"{commit or 'not recorded'} |")
    return "\n".join([
        "# Benchmark pages",
        "",
        "Every table the guides quote ([benchmarks](../benchmarks.md), [lego](../benchmarks_lego.md), "
        "[800×800 scenes](../benchmarks_800px.md)), as a bench command wrote it: `--page PATH` writes its table "
        "there as a page and this index again (`bench.pages.write_index`). A page's name says its scene and "
        "size; the page says its machine.",
        "",
        "| page | opens with | made by | commit |",
        "| --- | --- | --- | --- |",
        *rows,
        "",
    ])


def write_index(folder: Path) -> Path:
    """Writes ``folder``'s index; returns its path."""
    index = folder / INDEX_NAME
    index.write_text(index_markdown(folder), encoding="utf-8")
    return index


def publish_page(markdown: Path, page: Path, plot: Path | None = None, command: str | None = None) -> Path:
    """Copies a bench command's ``markdown`` table to ``page`` (with ``command`` and the
    source's commit where the table does not say them; its ``plot``, where it made one,
    beside it as ``PAGE.png`` and shown at the page's end) and rewrites the index of the page's
    folder; returns the page."""
    if page.suffix != ".md" or page.name == INDEX_NAME:
        raise NerfError(f"--page {page}: a page is a .md file other than the index ({INDEX_NAME})")
    page.parent.mkdir(parents=True, exist_ok=True)
    text = markdown.read_text(encoding="utf-8")
    if page_provenance(text)[1] is None:
        text = text.rstrip("\n") + "\n\n" + provenance_line(provenance(command)) + "\n"
    if plot is not None and plot.is_file():
        shutil.copyfile(plot, page.with_suffix(".png"))
        text = text.rstrip("\n") + f"\n\n![{page.stem}]({page.stem}.png)\n"
    page.write_text(text, encoding="utf-8")
    write_index(page.parent)
    return page
