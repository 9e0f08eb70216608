"""Shared fixtures: a tiny dataset rendered by real Blender (the bpy module) through the
generator's own command line, and runs trained on it, made once and kept in a cache on disk
keyed by their settings and the code that made them (``cached_fixture``); each test session
(each pytest-xdist worker) takes its own copy."""

from __future__ import annotations

import atexit
import functools
import hashlib
import importlib.metadata
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from filelock import FileLock, Timeout
from warm_python import WarmInterpreter

# The tests run the backend in their own processes too (train(), evaluate_run()...), where
# nerf_backend/__main__.py's sleeping OpenMP threads are not set: under pytest-xdist's two
# workers, one worker's spinning threads took the cores the other's work needed (a bfloat16
# training of 300 steps beside a training process: 101 s spinning, 18.8 s sleeping). Set
# before any test module loads torch; the user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# Under pytest-xdist the cores are shared out between the workers (two on two cores: a thread
# each), for the tests' own processes and what they start; a run that takes torch's thread
# count still splits its work over several threads where a kernel's test asks for them
# (test_compiled_*.py, test_sparse_grid.py: 1, 2 and 3). Two trainings side by side of fast's
# 300 steps on the tiny demo: 14.3 s with two threads each, 12.4 s with one.
XDIST_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if XDIST_WORKERS > 1:
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // XDIST_WORKERS)))

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = REPO_ROOT.parent / "shared"

# Small enough for 2 cores, large enough to train on: 40×40, 30 training views.
TINY_DEMO_ARGS = ["--demo", "--resolution", "40", "--train-views", "30", "--val-views", "2",
                  "--test-views", "4", "--samples", "16", "--seed", "0"]


# The test files that take longest, longest first (a cold run on 2 cores, session 58: 165 s to
# 32 s each). `make test` runs with pytest-xdist's `--dist loadfile --no-loadscope-reorder`: it
# hands each worker the next whole file in the collection's order. By default it orders files by
# their count of tests, which put the asset pipeline's one long test last, alone on one worker
# while the other had finished. The add-on session goes first, as it needs none of the shared
# trained runs, while the other worker's add-on jobs make the preview and surface runs that the
# next files wait for (the asset pipeline's default test uses the surface run since session 60).
LONGEST_FILES = ("test_addon.py", "test_addon_jobs.py", "test_training_extremes.py", "test_bench.py",
                 "test_asset_pipeline.py", "test_collapse_guard.py", "test_view_server.py", "test_bad_input.py",
                 "test_bench_suite.py", "test_datasets_gen_runs.py", "test_report.py", "test_training.py",
                 "test_budget_schedule.py", "test_first_run.py", "test_datasets_gen_scenes.py")


def pytest_collection_modifyitems(config, items):
    """The longest files first, then the rest in their own order (the sort is stable)."""
    rank = {name: position for position, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


# x86 instruction-set levels below AVX-512 and what the CPU needs to run each: the kernels'
# vectors are 4 floats wide at x86-64 (SSE2), 8 at x86-64-v3 (AVX2, the AVX2 machines' code).
X86_LEVELS = {"x86-64": {"sse2"}, "x86-64-v3": {"avx2", "fma", "bmi2", "f16c", "movbe"}}


def cpu_runs_x86_level(level: str) -> bool:
    """Whether this CPU runs code built for ``-march=LEVEL`` (one of X86_LEVELS), from the
    instruction-set flags the kernels' cache is keyed on."""
    import platform

    from nerf_backend.kernels.build import cpu_identity
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    flags = {flag for line in cpu_identity().splitlines() if line.startswith("flags")
             for flag in line.split(":", 1)[1].split()}
    return X86_LEVELS[level] <= flags


WARM = WarmInterpreter(REPO_ROOT)
atexit.register(WARM.stop)


def run_python(*args: str, timeout: float = 900, check: bool = True, **kwargs) -> subprocess.CompletedProcess:
    """Run ``python ARGS`` with this interpreter from the repo root, capturing output: a backend
    command forked from the warm interpreter (tests/warm_python.py: torch already imported), any
    other cold."""
    env = kwargs.get("env", os.environ)
    warm = set(kwargs) <= {"env"} and not os.environ.get("NERF_TESTS_COLD") and WARM.can_run(args, env)
    if os.environ.get("NERF_TESTS_PROCESS_LOG"):
        with open(os.environ["NERF_TESTS_PROCESS_LOG"], "a") as log:
            log.write(f"{'warm' if warm else 'cold'} {' '.join(args[:3])[:120]!r}\n")
    if warm:
        result = WARM.run(args, REPO_ROOT, dict(env), timeout)
    else:
        result = subprocess.run([sys.executable, *args], cwd=REPO_ROOT, capture_output=True, text=True,
                                timeout=timeout, **kwargs)
    if check and result.returncode != 0:
        raise AssertionError(f"python {' '.join(args)} exited {result.returncode}\n"
                             f"stdout:\n{result.stdout[-3000:]}\nstderr:\n{result.stderr[-3000:]}")
    return result


# Where fixtures that train or render are kept between test sessions, one folder a fixture and
# key: NERF_TEST_CACHE, else the user's cache folder.
FIXTURE_CACHE = Path(os.environ.get("NERF_TEST_CACHE") or Path.home() / ".cache" / "nerf-from-blender" / "test-fixtures")
# What a fixture's files depend on besides its own settings: the code that makes them.
CODE_FOLDERS = ("nerf_backend", "datasets_gen", "nerf_contract")
# A fixture's key unused this long is removed when the fixture is next made under another key.
STALE_AFTER_S = 24 * 3600


@functools.cache
def code_digest() -> str:
    """A digest of every file of the backend, the generator and the contract, and of the Python,
    torch and bpy that run them: a fixture made by other code is never reused."""
    digest = hashlib.sha256()
    for folder in CODE_FOLDERS:
        for path in sorted((REPO_ROOT / folder).rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                digest.update(str(path.relative_to(REPO_ROOT)).encode() + b"\0" + path.read_bytes() + b"\0")
    for package in ("torch", "bpy", "numpy"):
        try:
            digest.update(f"{package} {importlib.metadata.version(package)}".encode())
        except importlib.metadata.PackageNotFoundError:
            digest.update(f"{package} absent".encode())
    digest.update(sys.version.encode())
    return digest.hexdigest()[:16]


def cached_fixture(name: str, settings: list[str], make: Callable[[Path], None]) -> Path:
    """The folder ``make(folder)`` fills, kept in FIXTURE_CACHE under a key of ``settings`` and
    ``code_digest()``: made once, by whichever process (pytest-xdist's workers, a second
    ``make test``) asks first under the key's file lock, and reused while the code and settings
    stay the same. A maker that failed leaves no ``.done`` mark, so the next one starts afresh.
    Each use marks the key as used; making a key removes the same fixture's keys unused for
    STALE_AFTER_S (not sooner: two checkouts of different code testing at once each use their
    own key, and one removing the other's while it was being copied failed the other's tests).
    Read it, never write into it: ``own_copy`` gives a test session its own."""
    key = hashlib.sha256("\0".join([code_digest(), name, *settings]).encode()).hexdigest()[:16]
    FIXTURE_CACHE.mkdir(parents=True, exist_ok=True)
    folder = FIXTURE_CACHE / f"{name}-{key}"
    done = folder.with_name(folder.name + ".done")
    with FileLock(str(folder.with_name(folder.name + ".lock"))):
        if not (done.is_file() and folder.is_dir()):
            shutil.rmtree(folder, ignore_errors=True)
            make(folder)
            for stale in FIXTURE_CACHE.glob(f"{name}-*.done"):
                if stale != done and time.time() - stale.stat().st_mtime > STALE_AFTER_S:
                    try:  # and not while another session holds it
                        with FileLock(str(stale.with_suffix(".lock")), timeout=0):
                            stale.unlink(missing_ok=True)
                            shutil.rmtree(stale.with_suffix(""), ignore_errors=True)
                    except Timeout:
                        pass
        done.touch()
    return folder


def own_copy(tmp_path_factory, folder: Path) -> Path:
    """This session's own copy of a cached fixture: tests that write into it (renders, reports)
    never race another worker's or change the cache."""
    own = tmp_path_factory.mktemp(folder.name) / folder.name.rsplit("-", 1)[0]
    shutil.copytree(folder, own, symlinks=True)
    return own


@pytest.fixture(scope="session")
def tiny_demo_source() -> Path:
    """The demo scene rendered by Cycles at 40×40 (30 train, 2 val, 4 test views), in the fixture
    cache: the dataset the shared runs train on (read only)."""
    return cached_fixture("tiny_demo", TINY_DEMO_ARGS,
                          lambda out: run_python("-m", "datasets_gen", *TINY_DEMO_ARGS, "--out", str(out)))


@pytest.fixture(scope="session")
def tiny_demo_dataset(tiny_demo_source, tmp_path_factory) -> Path:
    """This session's copy of the tiny demo dataset."""
    return own_copy(tmp_path_factory, tiny_demo_source)


@pytest.fixture(scope="session")
def shared_scenes() -> Path:
    path = SHARED_DIR / "scenes"
    if not path.is_dir():
        pytest.fail(f"{path} is missing: the project's tests need ../shared/scenes beside the repo")
    return path


def _trained(tmp_path_factory, dataset: Path, name: str, *arguments: str) -> Path:
    """A copy of the run ``train DATASET ARGUMENTS`` makes, trained once into the fixture cache;
    its config names the cached dataset."""
    # Every core: the other worker is most often waiting for the same run.
    every_core = dict(os.environ, OMP_NUM_THREADS=str(os.cpu_count() or 1))
    return own_copy(tmp_path_factory, cached_fixture(name, [dataset.name, *arguments], lambda run: run_python(
        "-m", "nerf_backend", "train", str(dataset), "--out", str(run), *arguments, "--no-progress", env=every_core)))


TRAIN_ITERS = 250
# Half preview's 512 rays a step: its network is the same, and 250 steps still score 25.35 dB
# against test_training's floor of 21 (512 rays: 26.1) in 27 s of training, not 51.
TRAIN_RAYS = 256
# And half its samples a ray (16 coarse, 16 fine): a 40-pixel view needs no more, the network's
# products are the step's cost, and 250 steps score 25.21 dB (32 + 32: 25.35) in 17.7 s, not 33
# (learning rate 0: 16.75 dB, so the floor still catches a run that does not learn).
TRAIN_SAMPLES = 16


@pytest.fixture(scope="session")
def trained_run(tiny_demo_source, tmp_path_factory) -> Path:
    """The preview preset trained for TRAIN_ITERS iterations of TRAIN_RAYS rays of TRAIN_SAMPLES
    coarse and fine samples on the tiny demo dataset."""
    return _trained(tmp_path_factory, tiny_demo_source, "preview_run", "--preset", "preview", "--iters", str(TRAIN_ITERS),
                    "--set", f"rays_per_batch={TRAIN_RAYS}", "--set", f"sampling.coarse_samples={TRAIN_SAMPLES}",
                    "--set", f"sampling.fine_samples={TRAIN_SAMPLES}")


MARCHED_ITERS = 300
# A checkpoint every 20 steps: tests/test_training_extremes.py's kill -9 test kills a training of
# these settings between several of them and compares the resumed run with this one.
MARCHED_SETTINGS = ("checkpoint_every=20",)


@pytest.fixture(scope="session")
def trained_marched_run(tiny_demo_source, tmp_path_factory) -> Path:
    """The fast preset (a marched grid) trained for MARCHED_ITERS steps on the tiny demo dataset."""
    return _trained(tmp_path_factory, tiny_demo_source, "fast_run", "--preset", "fast", "--iters", str(MARCHED_ITERS),
                    *(argument for setting in MARCHED_SETTINGS for argument in ("--set", setting)))


@pytest.fixture(scope="session")
def trained_surface_run(tiny_demo_source, tmp_path_factory) -> Path:
    """The surface preset trained for 400 steps on the tiny demo dataset (from its prior)."""
    return _trained(tmp_path_factory, tiny_demo_source, "surface_run", "--preset", "surface", "--iters", "400")


def camera_path_through_test_views(dataset: Path, folder: Path, repeats: int = 1, copy_images: bool = True) -> tuple:
    """A camera path (``folder/camera_path.json``) through the dataset's test views, ``repeats``
    times over, whose 'Cycles' frames are those views' images: scoring it must give ``eval``'s
    numbers. Returns the path, its frame count and the ``(image, cycles frame)`` pairs; the
    images are copied in unless ``copy_images`` is False (a job's stage copies them)."""
    import json
    import shutil

    test = json.loads((dataset / "transforms_test.json").read_text())
    frames, pairs = [], []
    for index in range(repeats * len(test["frames"])):
        view = test["frames"][index % len(test["frames"])]
        stem = f"{index + 1:04d}"
        frames.append({"frame": index + 1, "transform_matrix": view["transform_matrix"],
                       "cycles_file_path": f"cycles/{stem}.png",
                       **{key: test[key] for key in ("w", "h", "fl_x", "fl_y", "cx", "cy")}})
        pairs.append((dataset / f"{view['file_path']}.png", folder / "cycles" / f"{stem}.png"))
    (folder / "cycles").mkdir(parents=True, exist_ok=True)
    path = folder / "camera_path.json"
    path.write_text(json.dumps({"camera": "test views", "fps": 12, "frames": frames}))
    if copy_images:
        for source, target in pairs:
            shutil.copy(source, target)
    return path, len(frames), pairs


def rays_through_box(box, count: int, seed: int):
    """``count`` rays from a sphere of radius 4 towards random points of ``box`` (a
    ``SceneBounds``): origins, unit directions, and where each enters and leaves the box."""
    import torch
    from nerf_backend.core.cameras import ray_box_intersection

    generator = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1) * 4.0
    targets = (torch.rand(count, 3, generator=generator) * 2 - 1) * torch.tensor(box.box_max)
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    near, far, _ = ray_box_intersection(origins, directions, torch.tensor(box.box_min), torch.tensor(box.box_max))
    return origins, directions, near, far


def deferred_grid_model(box, seed: int):
    """The auto preset's grid model with deferred colour over ``box`` (a ``SceneBounds``), random
    smooth density blobs (random values on a coarse grid, interpolated up) and random appearance,
    its occupancy updated and neither all empty nor all full; in inference mode, rendering no
    sample that training would skip (``render_alpha_threshold`` 0)."""
    import dataclasses

    import torch
    from nerf_backend.configs.presets import PRESETS
    from nerf_backend.models.registry import build_model

    torch.manual_seed(seed)
    config = dataclasses.replace(PRESETS["auto"], render_alpha_threshold=0.0)
    config = config.with_settings(grid=dataclasses.replace(config.grid, deferred_colour=True))
    model = build_model(config, box)
    vertices = model.field.vertices
    model.resize((5, 6, 4))
    with torch.no_grad():
        for parameter in model.field.encoding_parameters():
            parameter.normal_(0.0, 1.4)
    model.resize(vertices)
    model.update_occupancy()
    assert 0.01 < model.occupancy.occupied_fraction < 0.98
    return model.eval()
