"""The packages' boundaries and dependency graphs, read from the source with ``ast`` (imports
inside functions included, since they hide real dependencies just the same): no module of
``nerf_backend``, ``datasets_gen`` or ``addon`` depends on itself through others, each imports
only its own layer and lower ones, the backend never imports ``bpy``, the generator's and the
add-on's plain sides (``datasets_gen.core`` and ``.io``, ``addon.core``) never import Blender's
modules, the add-on never imports torch or the backend, and the generator never imports torch."""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest
import tomllib
from conftest import REPO_ROOT


def _module_name(package: Path, path: Path) -> str:
    parts = list(path.relative_to(REPO_ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    path = REPO_ROOT.joinpath(*name.split("."))
    return path.is_dir() or path.with_suffix(".py").is_file()


def _resolve(here: list[str], node: ast.ImportFrom) -> list[str]:
    """The absolute names an ``from ... import`` statement imports (relative ones resolved):
    the module it imports from, and each name it takes that is itself one of our modules."""
    base = here[:len(here) - node.level + 1] if node.level else []
    if node.module:
        module = ".".join([*base, node.module])
        return [module] + [f"{module}.{alias.name}" for alias in node.names if _is_module(f"{module}.{alias.name}")]
    return [".".join([*base, alias.name]) for alias in node.names]


def _import_nodes(package: Path):
    """(module name, import statement, whether it is at the top of its module) for every import
    statement of ``package``'s modules, relative names resolved by ``_names``."""
    for path in sorted(package.rglob("*.py")):
        name = _module_name(package, path)
        here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        tree = ast.parse(path.read_text(encoding="utf-8"))
        top = {id(node) for node in tree.body}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                yield name, [alias.name for alias in node.names], id(node) in top
            elif isinstance(node, ast.ImportFrom):
                yield name, _resolve(here, node), id(node) in top


def _imports(package: Path) -> dict[str, set[str]]:
    """Each module of ``package`` → the absolute names it imports (relative ones resolved)."""
    graph = {_module_name(package, path): set() for path in sorted(package.rglob("*.py"))}
    for module, names, _ in _import_nodes(package):
        graph[module].update(names)
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


LAYERED = ("nerf_backend", "datasets_gen", "addon")


@pytest.mark.parametrize("package", LAYERED)
def test_no_import_cycle(package):
    graph = _imports(REPO_ROOT / package)
    assert len(graph) > 20, sorted(graph)  # the walk found the package
    assert _cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"p.a": {"p.b"}, "p.b": {"p.c.x"}, "p.c": {"p.a"}, "p.d": {"numpy"}}) == [["p.a", "p.b", "p.c", "p.a"]]


BLENDER_MODULES = ("bpy", "bpy_extras", "bmesh", "mathutils", "gpu", "gpu_extras", "blf", "bl_ui", "addon_utils")


def test_no_import_cycle_across_the_repository():
    graph = {}
    for package in ("addon", "datasets_gen", "nerf_backend", "nerf_contract"):
        graph.update(_imports(REPO_ROOT / package))
    assert _cycles(graph) == []


@pytest.mark.parametrize("package, forbidden", [
    ("nerf_backend", (*BLENDER_MODULES, "addon", "datasets_gen")),
    ("addon", ("torch", "nerf_backend", "importlib")),  # the backends only through static imports
    ("datasets_gen", ("torch", "nerf_backend", "addon")),
    # The contract: standard library only, so that all three can import it.
    ("nerf_contract", (*BLENDER_MODULES, "torch", "numpy", "addon", "datasets_gen", "nerf_backend")),
    ("datasets_gen.core", BLENDER_MODULES),  # the plain side runs in any Python
    ("datasets_gen.io", BLENDER_MODULES),
    ("addon.core", BLENDER_MODULES),  # the add-on's plain side, tested without Blender
])
def test_packages_keep_to_their_side(package, forbidden):
    offending = {module: sorted(name for name in names if name.split(".")[0] in forbidden)
                 for module, names in _imports(REPO_ROOT.joinpath(*package.split("."))).items()}
    assert {module: names for module, names in offending.items() if names} == {}


# Each package's layers, lowest first: a module may import from its own sub-package and from
# sub-packages of lower layers only ("" is the modules at the top: commands and pipelines).
LAYERS = {
    "nerf_backend": (
        ("core", "kernels"),  # kernels: plain C sources and their builder
        ("data", "field_components", "model_components", "metrics"),
        ("fields",),
        ("models",),
        ("configs",),
        ("planning",),  # a run planned in one pass: facts, rules, the frozen plan
        ("evaluation",),
        ("asset",),  # export: a trained surface baked into a glTF asset
        ("training",),
        ("bench",),
        ("commands",),  # one module a command
        ("",),  # cli, demo, __main__
    ),
    # As Blender's glTF add-on keeps io/ apart from blender/: the plain side below the bpy side.
    "datasets_gen": (
        ("core",),  # options, camera maths, scene checks, voxels, z-buffer
        ("io",),  # the dataset folder and its files
        ("blender",),  # bpy
        ("",),  # generator, suite, camera_path_export, cli, generate, __main__
    ),
    # The same split in the add-on: the plain side below the one that runs only in Blender.
    "addon": (
        ("core",),  # jobs, Set Up Backend, the live view's client, pixels, the panel's wording
        ("blender",),  # bpy: registration, properties, operators, the panel, timers, draw handlers
        ("",),  # __init__: the extension's entry, which registers blender/
    ),
}


def _layer_of(package: str) -> dict[str, int]:
    return {sub: rank for rank, subs in enumerate(LAYERS[package]) for sub in subs}


def _layer_package(package: str, name: str) -> str:
    """The sub-package of ``package`` a module is in ("" for the modules at the top)."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 and (REPO_ROOT / package / parts[1]).is_dir() else ""


def test_the_addon_is_its_entry_and_its_two_sides():
    """Whether a file of the add-on runs without Blender is said by its folder alone."""
    addon = REPO_ROOT / "addon"
    assert sorted(path.name for path in addon.glob("*.py")) == ["__init__.py"]
    assert sorted(path.name for path in addon.iterdir() if path.is_dir() and path.name != "__pycache__") == [
        "blender", "core"]


@pytest.mark.parametrize("package", LAYERED)
def test_every_module_belongs_to_a_layer(package):
    graph = _imports(REPO_ROOT / package)
    assert {_layer_package(package, module) for module in graph} <= set(_layer_of(package))


@pytest.mark.parametrize("package", LAYERED)
def test_modules_import_only_their_own_layer_package_or_lower_ones(package):
    layer_of, upward = _layer_of(package), []
    for module, names in _imports(REPO_ROOT / package).items():
        source = _layer_package(package, module)
        for name in names:
            if name.split(".")[0] != package or name == package:
                continue
            target = _layer_package(package, name)
            if target != source and layer_of[target] >= layer_of[source]:
                upward.append(f"{module} imports {name}")
    assert upward == []


# Imports deferred on purpose, with the reason: optional or heavy libraries, platform modules,
# and Blender's modules where a command must answer bad input before Blender loads (the bpy
# module takes seconds to import, or is absent). Every other import is at the top of its module,
# where the graph shows it.
DEFERRED_IMPORTS = {
    "nerf_backend.__main__": {"torch"},  # checked first, for a one-line error without it
    "nerf_backend.core.files": {"OpenEXR"},  # only depth files need it
    "nerf_backend.core.plotting": {"matplotlib", "matplotlib.pyplot"},  # half a second; pictures only
    "nerf_backend.metrics.geometry": {"scipy.spatial"},  # a quarter second; geometry scores only
    # scipy.ndimage: 0.3 s of every command's start (a third of ours), needed by few of them.
    "nerf_backend.metrics.image_metrics": {"skimage.metrics"},  # SSIM only; it brings scipy.ndimage
    "nerf_backend.model_components.occupancy": {"scipy"},  # the prior's pieces only
    "nerf_backend.field_components.surface_band": {"scipy"},  # surfaces only
    "nerf_backend.field_components.distance_transform": {"scipy"},  # the fallback only
    "nerf_backend.bench.tables": {"matplotlib.lines", "matplotlib.patches"},
    "nerf_backend.data.run_folder": {"fcntl", "msvcrt"},  # one per platform
    "datasets_gen.core.progress": {"tqdm"},  # optional: Blender's own Python lacks it
    "datasets_gen.io.output_dir": {"numpy"},  # only the occupancy prior needs it; Debian's Blender lacks it
    "datasets_gen.io.formats": {"datasets_gen.io.colmap_export"},  # numpy, as above
    "datasets_gen.generate": {"bpy", "datasets_gen.cli", "traceback"},  # a script: sys.path is set first
    # The pipelines: bad input is refused before the Blender side loads.
    "datasets_gen.cli": {"datasets_gen.generator", "datasets_gen.suite", "datasets_gen.camera_path_export",
                         "datasets_gen.asset_render", "datasets_gen.core.builtin_scenes",
                         "datasets_gen.core.camera_path", "datasets_gen.io.shards"},
    "datasets_gen.generator": {"bpy", "numpy", "datasets_gen.blender.scene_state", "datasets_gen.blender.render",
                               "datasets_gen.blender.scene_bounds", "datasets_gen.blender.scene_facts",
                               "datasets_gen.blender.scene_occupancy", "datasets_gen.blender.builtin_scenes",
                               "datasets_gen.io.surface_mesh"},
    "datasets_gen.suite": {"bpy", "datasets_gen.generator", "datasets_gen.blender.scene_facts"},
    "datasets_gen.camera_path_export": {"bpy", "datasets_gen.generator", "datasets_gen.blender.camera_animation",
                                        "datasets_gen.blender.scene_bounds"},
    "datasets_gen.asset_render": {"bpy", "datasets_gen.generator", "datasets_gen.blender.compat",
                                  "datasets_gen.blender.render"},
    # The extension's entry: its plain side is imported (the tests) where bpy is not.
    "addon": {"addon.blender", "addon.blender.operators", "addon.blender.panel", "addon.blender.properties"},
}


@pytest.mark.parametrize("package", LAYERED)
def test_imports_are_at_the_top_of_modules(package):
    deferred = {}
    for module, names, at_top in _import_nodes(REPO_ROOT / package):
        if not at_top:
            deferred.setdefault(module, set()).update(names)
    assert deferred == {module: names for module, names in DEFERRED_IMPORTS.items()
                        if module == package or module.startswith(package + ".")}


# What each third-party module the backend imports is installed as.
DISTRIBUTIONS = {"PIL": "pillow", "skimage": "scikit-image", "OpenEXR": "OpenEXR", "imageio_ffmpeg": "imageio-ffmpeg",
                 "fast_simplification": "fast-simplification"}


def _requirement_names(lines: list[str]) -> set[str]:
    return {re.split(r"[<>=!~\[ ]", line.strip(), maxsplit=1)[0].lower() for line in lines
            if line.strip() and not line.strip().startswith("#")}


def test_the_backend_requirements_cover_its_imports():
    """The add-on's Set Up Backend installs nerf_backend/requirements.txt into a fresh Python:
    a module the backend imports but the file lacks would break every command there."""
    imported = set()
    for names in _imports(REPO_ROOT / "nerf_backend").values():
        imported.update(name.split(".")[0] for name in names)
    ours = {"nerf_backend", "nerf_contract"}  # nerf_contract travels beside the backend (its PYTHONPATH)
    third_party = {name for name in imported if name not in sys.stdlib_module_names and name not in ours}
    needed = {DISTRIBUTIONS.get(name, name).lower() for name in third_party}
    requirements = _requirement_names((REPO_ROOT / "nerf_backend" / "requirements.txt").read_text().splitlines())
    project = _requirement_names(tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["dependencies"])
    assert needed - requirements == set()
    assert needed - project == set()


# What the add-on's Blender side (addon.blender) imports of datasets_gen's Blender side and its
# pipelines: the scene checks and the in-process render (Generate Dataset without a Blender
# binary), the Cycles render of Compare with Cycles, and a camera's path. Everything else the
# add-on takes from datasets_gen is the plain side (core, io), and from the backend only
# nerf_contract.
ADDON_BLENDER_SIDE = {"datasets_gen.generator", "datasets_gen.camera_path_export", "datasets_gen.blender.compat",
                      "datasets_gen.blender.render", "datasets_gen.blender.scene_state"}


def test_the_addon_reaches_the_backends_through_the_contract_and_the_generators_plain_side():
    links = {}
    for module, names in _imports(REPO_ROOT / "addon").items():
        for name in names:
            if name.split(".")[0] in ("datasets_gen", "nerf_contract"):
                links.setdefault(module, set()).add(name)
    assert links, "the walk found the add-on's imports"
    outside = {}
    for module, names in links.items():
        for name in names:
            # The bare package: core/sources.py takes its folder from it (its __init__ needs no bpy).
            plain = name in ("nerf_contract", "datasets_gen", "datasets_gen.blender") or name.startswith(
                ("nerf_contract.", "datasets_gen.core", "datasets_gen.io"))
            allowed = plain or (name in ADDON_BLENDER_SIDE and module.startswith("addon.blender."))
            if not allowed:
                outside.setdefault(module, []).append(name)
    assert outside == {}


MAX_FUNCTION_LINES = 80  # a function longer than a screen is split where its steps are


def test_no_function_is_longer_than_a_screen():
    long = []
    for package in ("addon", "datasets_gen", "nerf_backend", "nerf_contract"):
        for path in sorted((REPO_ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    lines = node.end_lineno - node.lineno + 1
                    if lines > MAX_FUNCTION_LINES:
                        long.append(f"{path.relative_to(REPO_ROOT)}:{node.lineno} {node.name} ({lines} lines)")
    assert long == []
