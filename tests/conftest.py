"""Shared fixtures: a tiny dataset rendered by real Blender (the bpy module) through the
generator's own command line, and runs trained on it, once per test session: under
pytest-xdist (``make test`` runs two workers), once for all workers."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from filelock import FileLock

# The tests run the backend in their own processes too (train(), evaluate_run()...), where
# nerf_backend/__main__.py's sleeping OpenMP threads are not set: under pytest-xdist's two
# workers, one worker's spinning threads took the cores the other's work needed (a bfloat16
# training of 300 steps beside a training process: 101 s spinning, 18.8 s sleeping). Set
# before any test module loads torch; the user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = REPO_ROOT.parent / "shared"

# Small enough for 2 cores, large enough to train on: 40×40, 30 training views.
TINY_DEMO_ARGS = ["--demo", "--resolution", "40", "--train-views", "30", "--val-views", "2",
                  "--test-views", "4", "--samples", "16", "--seed", "0"]


def run_python(*args: str, timeout: float = 900, check: bool = True, **kwargs) -> subprocess.CompletedProcess:
    """Run ``python ARGS`` with this interpreter from the repo root, capturing output."""
    result = subprocess.run([sys.executable, *args], cwd=REPO_ROOT, capture_output=True, text=True,
                            timeout=timeout, **kwargs)
    if check and result.returncode != 0:
        raise AssertionError(f"python {' '.join(args)} exited {result.returncode}\n"
                             f"stdout:\n{result.stdout[-3000:]}\nstderr:\n{result.stderr[-3000:]}")
    return result


def made_once(tmp_path_factory, name: str, make: Callable[[Path], None]) -> Path:
    """A folder ``make(folder)`` fills, made once per test session. Under pytest-xdist the first
    worker to ask makes it (under a file lock) and each worker gets its own copy, so that tests
    which write into it (renders, reports) never race another worker's."""
    own = tmp_path_factory.mktemp(name) / name
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        make(own)
        return own
    shared_root = tmp_path_factory.getbasetemp().parent  # the same for every worker of this run
    shared, done = shared_root / name, shared_root / f"{name}.done"
    with FileLock(str(shared_root / f"{name}.lock")):
        if not done.is_file():  # a worker that failed to make it left no mark: the next one tries again
            shutil.rmtree(shared, ignore_errors=True)
            make(shared)
            done.touch()
    shutil.copytree(shared, own, symlinks=True)
    return own


@pytest.fixture(scope="session")
def tiny_demo_dataset(tmp_path_factory) -> Path:
    """The demo scene rendered by Cycles at 40×40 (30 train, 2 val, 4 test views)."""
    return made_once(tmp_path_factory, "tiny_demo",
                     lambda out: run_python("-m", "datasets_gen", *TINY_DEMO_ARGS, "--out", str(out)))


@pytest.fixture(scope="session")
def shared_scenes() -> Path:
    path = SHARED_DIR / "scenes"
    if not path.is_dir():
        pytest.fail(f"{path} is missing: the project's tests need ../shared/scenes beside the repo")
    return path


TRAIN_ITERS = 400


@pytest.fixture(scope="session")
def trained_run(tiny_demo_dataset, tmp_path_factory) -> Path:
    """The preview preset trained for TRAIN_ITERS iterations on the tiny demo dataset."""
    return made_once(tmp_path_factory, "preview_run", lambda run: run_python(
        "-m", "nerf_backend", "train", str(tiny_demo_dataset), "--preset", "preview", "--out", str(run),
        "--iters", str(TRAIN_ITERS), "--no-progress"))


@pytest.fixture(scope="session")
def trained_marched_run(tiny_demo_dataset, tmp_path_factory) -> Path:
    """The fast preset (a marched grid) trained for 300 steps on the tiny demo dataset."""
    return made_once(tmp_path_factory, "fast_run", lambda run: run_python(
        "-m", "nerf_backend", "train", str(tiny_demo_dataset), "--preset", "fast", "--iters", "300",
        "--out", str(run), "--no-progress"))


@pytest.fixture(scope="session")
def trained_surface_run(tiny_demo_dataset, tmp_path_factory) -> Path:
    """The surface preset trained for 600 steps on the tiny demo dataset (from its prior)."""
    return made_once(tmp_path_factory, "surface_run", lambda run: run_python(
        "-m", "nerf_backend", "train", str(tiny_demo_dataset), "--preset", "surface", "--iters", "600",
        "--out", str(run), "--no-progress"))


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
