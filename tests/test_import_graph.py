"""The packages' boundaries and the backend's dependency graph, read from the source with
``ast`` (imports inside functions included, since they hide real dependencies just the same):
no module of ``nerf_backend`` depends on itself through others, the backend never imports
``bpy``, the add-on never imports torch or the backend, and the generator never imports torch."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from conftest import REPO_ROOT


def _module_name(package: Path, path: Path) -> str:
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(package: Path) -> dict[str, set[str]]:
    """Each module of ``package`` → the absolute names it imports (relative ones resolved)."""
    graph = {}
    for path in sorted(package.rglob("*.py")):
        name = _module_name(package, path)
        here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        found = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = here[:len(here) - node.level + 1] if node.level else []
                if node.module:
                    found.add(".".join([*base, node.module]))
                else:
                    found.update(".".join([*base, alias.name]) for alias in node.names)
        graph[name] = found
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Cycles among the graph's own modules (an import of ``a.b.c`` counts for ``a.b.c`` if it is
    a module, else for the package ``a.b`` it names a member of)."""
    own = {module: {name if name in graph else name.rpartition(".")[0] for name in names} & set(graph)
           for module, names in graph.items()}
    found, state, path = [], {}, []

    def visit(module: str) -> None:
        state[module] = "open"
        path.append(module)
        for target in sorted(own[module]):
            if state.get(target) == "open":
                found.append(path[path.index(target):] + [target])
            elif target not in state:
                visit(target)
        path.pop()
        state[module] = "done"

    for module in sorted(own):
        if module not in state:
            visit(module)
    return found


def test_the_backend_has_no_import_cycle():
    graph = _imports(REPO_ROOT / "nerf_backend")
    assert len(graph) > 30, sorted(graph)  # the walk found the package
    assert _cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"p.a": {"p.b"}, "p.b": {"p.c.x"}, "p.c": {"p.a"}, "p.d": {"numpy"}}) == [["p.a", "p.b", "p.c", "p.a"]]


@pytest.mark.parametrize("package, forbidden", [
    ("nerf_backend", ("bpy", "mathutils", "addon", "datasets_gen")),
    ("addon", ("torch", "nerf_backend")),
    ("datasets_gen", ("torch", "nerf_backend", "addon")),
])
def test_packages_keep_to_their_side(package, forbidden):
    offending = {module: sorted(name for name in names if name.split(".")[0] in forbidden)
                 for module, names in _imports(REPO_ROOT / package).items()}
    assert {module: names for module, names in offending.items() if names} == {}
