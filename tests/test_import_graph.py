"""The packages' boundaries and the backend's dependency graph, read from the source with
``ast`` (imports inside functions included, since they hide real dependencies just the same):
no module of ``nerf_backend`` depends on itself through others, the backend never imports
``bpy``, the add-on never imports torch or the backend, and the generator never imports torch."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
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


# The backend's layers, lowest first: a module may import from its own package and from
# packages of lower layers only (README, "How the code is laid out").
BACKEND_LAYERS = (
    ("core",),
    ("data", "field_components", "model_components", "metrics"),
    ("fields",),
    ("models",),
    ("configs",),
    ("evaluation",),
    ("training",),
    ("bench",),
    ("",),  # the modules at the top: cli, demo, __main__
)
LAYER_OF = {package: rank for rank, packages in enumerate(BACKEND_LAYERS) for package in packages}


def _layer_package(name: str) -> str:
    """The sub-package of ``nerf_backend`` a module is in ("" for the modules at the top)."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 and (REPO_ROOT / "nerf_backend" / parts[1]).is_dir() else ""


def test_every_backend_module_belongs_to_a_layer():
    graph = _imports(REPO_ROOT / "nerf_backend")
    assert {_layer_package(module) for module in graph} <= set(LAYER_OF)


def test_backend_modules_import_only_their_own_layer_package_or_lower_ones():
    upward = []
    for module, names in _imports(REPO_ROOT / "nerf_backend").items():
        source = _layer_package(module)
        for name in names:
            if name.split(".")[0] != "nerf_backend" or name == "nerf_backend":
                continue
            target = _layer_package(name)
            if target != source and LAYER_OF[target] >= LAYER_OF[source]:
                upward.append(f"{module} imports {name}")
    assert upward == []


# Imports deferred on purpose (each says why where it is): optional or heavy libraries and
# platform modules. Every other import is at the top of its module, where the graph shows it.
DEFERRED_IMPORTS = {
    "nerf_backend.__main__": {"torch"},  # checked first, for a one-line error without it
    "nerf_backend.core.files": {"OpenEXR"},  # only depth files need it
    "nerf_backend.core.plotting": {"matplotlib", "matplotlib.pyplot"},  # half a second; pictures only
    "nerf_backend.bench.tables": {"matplotlib.lines", "matplotlib.patches"},
    "nerf_backend.data.run_folder": {"fcntl", "msvcrt"},  # one per platform
}


def test_backend_imports_are_at_the_top_of_modules():
    package = REPO_ROOT / "nerf_backend"
    deferred = {}
    for path in sorted(package.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        top = {id(node) for node in tree.body}
        names = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)) and id(node) not in top:
                names.update(alias.name for alias in node.names) if isinstance(node, ast.Import) \
                    else names.add(node.module or "")
        if names:
            deferred[_module_name(package, path)] = names
    assert deferred == DEFERRED_IMPORTS


# What each third-party module the backend imports is installed as.
DISTRIBUTIONS = {"PIL": "pillow", "skimage": "scikit-image", "OpenEXR": "OpenEXR", "imageio_ffmpeg": "imageio-ffmpeg"}


def _requirement_names(lines: list[str]) -> set[str]:
    return {re.split(r"[<>=!~\[ ]", line.strip(), maxsplit=1)[0].lower() for line in lines
            if line.strip() and not line.strip().startswith("#")}


def test_the_backend_requirements_cover_its_imports():
    """The add-on's Set Up Backend installs nerf_backend/requirements.txt into a fresh Python:
    a module the backend imports but the file lacks would break every command there."""
    imported = set()
    for names in _imports(REPO_ROOT / "nerf_backend").values():
        imported.update(name.split(".")[0] for name in names)
    third_party = {name for name in imported if name not in sys.stdlib_module_names and name != "nerf_backend"}
    needed = {DISTRIBUTIONS.get(name, name).lower() for name in third_party}
    requirements = _requirement_names((REPO_ROOT / "nerf_backend" / "requirements.txt").read_text().splitlines())
    project = _requirement_names(tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["dependencies"])
    assert needed - requirements == set()
    assert needed - project == set()
