"""The front page stays a front page, and nothing it dropped is lost: the README is short, starts
with the two commands, and every page under docs/ is reachable from it through links that
resolve."""

from __future__ import annotations

import re
from pathlib import Path

from addon.core.torch_builds import CUDA_BUILDS, ROCM_BUILD
from nerf_backend.bench.pages import INDEX_NAME, index_markdown, page_provenance
from conftest import REPO_ROOT

README = REPO_ROOT / "README.md"
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _local_links(page: Path) -> list[Path]:
    targets = []
    for target in LINK.findall(page.read_text(encoding="utf-8")):
        path = target.split("#")[0]
        if path and not re.match(r"[a-z]+://", path):
            targets.append((page.parent / path).resolve())
    return targets


def test_the_readme_is_a_short_front_page_that_starts_with_the_two_commands():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 150
    first_block = text.split("```")[1]
    assert "make demo" in first_block and "make test" in first_block


def test_every_link_resolves_and_every_page_is_reachable_from_the_readme():
    pages = [README, *sorted((REPO_ROOT / "docs").rglob("*.md"))]
    broken = [f"{page.name} -> {target}" for page in pages for target in _local_links(page) if not target.exists()]
    assert not broken, broken
    reached, frontier = {README.resolve()}, [README]
    while frontier:
        for target in _local_links(frontier.pop()):
            if target.suffix == ".md" and target not in reached:
                reached.add(target)
                frontier.append(target)
    unreachable = [str(page.relative_to(REPO_ROOT)) for page in pages if page.resolve() not in reached]
    # The bench pages are reached from their index and the guides; a page nothing links to is lost.
    assert not unreachable, unreachable


def test_the_readme_names_every_pytorch_build_set_up_backend_can_choose():
    text = README.read_text(encoding="utf-8")
    for key in [key for key, _ in CUDA_BUILDS] + [ROCM_BUILD]:
        assert f"`{key}`" in text, key


def test_the_benchmark_pages_index_is_the_one_their_folder_gives():
    """docs/benchmarks/README.md is ``write_index``'s for the pages there: each listed with what
    it measures and the command and commit that made it (or that they were not recorded)."""
    folder = REPO_ROOT / "docs" / "benchmarks"
    assert (folder / INDEX_NAME).read_text(encoding="utf-8") == index_markdown(folder)
    pages = sorted(p.name for p in folder.glob("*.md") if p.name != INDEX_NAME)
    assert len(pages) >= 40
    linked = {target.name for target in _local_links(folder / INDEX_NAME)}
    assert set(pages) <= linked
    for name in pages:
        command, commit = page_provenance((folder / name).read_text(encoding="utf-8"))
        assert commit, f"{name}: no commit on the page"
