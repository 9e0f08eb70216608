"""The front page stays a front page, and nothing it dropped is lost: the README is short, starts
with the two commands, and every page under docs/ is reachable from it through links that
resolve."""

from __future__ import annotations

import re
from pathlib import Path

from addon.torch_builds import CUDA_BUILDS, ROCM_BUILD
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
    pages = [README, *sorted((REPO_ROOT / "docs").glob("*.md"))]
    broken = [f"{page.name} -> {target}" for page in pages for target in _local_links(page) if not target.exists()]
    assert not broken, broken
    reached, frontier = {README.resolve()}, [README]
    while frontier:
        for target in _local_links(frontier.pop()):
            if target.suffix == ".md" and target not in reached:
                reached.add(target)
                frontier.append(target)
    unreachable = [page.name for page in pages if page.resolve() not in reached]
    # The bench tables are reached from the benchmark pages; a page nothing links to is lost.
    assert not unreachable, unreachable


def test_the_readme_names_every_pytorch_build_set_up_backend_can_choose():
    text = README.read_text(encoding="utf-8")
    for key in [key for key, _ in CUDA_BUILDS] + [ROCM_BUILD]:
        assert f"`{key}`" in text, key
