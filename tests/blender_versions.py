"""The Blender versions users run, as ``bpy`` modules from PyPI, each in a virtual environment
of its own (one Python cannot hold two ``bpy`` versions), and how to run a script in each.

- The project's ``.venv`` holds 5.0.1 (requirements-dev.txt), on this machine's Python 3.11.
- 4.2 LTS (the manifest's minimum) and 4.5 LTS, also for Python 3.11: made here on first use
  and kept in ``.venv-bpy/VERSION/`` (about 1 GB and a minute each).
- 5.1 and 5.2 LTS: Blender 5.1 moved to Python 3.13 and their wheels are ``cp313`` only, so
  their venvs are made with Debian trixie's Python 3.13 inside the chroot of
  ``tests/blender_gui.py`` (``/opt/bpy/VERSION`` there), and the script runs there.

These Pythons run Blender only: the add-on's backend is still the project's ``.venv``, as a
user's Blender would point at a separate Python that has torch.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import blender_gui

REPO_ROOT = Path(__file__).resolve().parents[1]
VENVS = REPO_ROOT / ".venv-bpy"

# The newest patch release of each series on PyPI (2026-11-25).
LTS_VERSIONS = ("4.2.23", "4.5.15")  # Python 3.11
PY313_VERSIONS = ("5.1.2", "5.2.3")  # Python 3.13, in the trixie chroot
# Inside the chroot: a clean environment (the host's PATH and pip settings would leak in), and
# pip trusting the system's certificate authorities (the host's are copied in).
CHROOT_ENV = ("PATH=/usr/sbin:/usr/bin:/sbin:/bin", "PIP_CERT=/etc/ssl/certs/ca-certificates.crt",
              "PIP_DISABLE_PIP_VERSION_CHECK=1")


def bpy_python(version: str) -> Path:
    """A Python 3.11 with ``bpy==version`` (made on first use); raises with pip's output on failure."""
    venv = VENVS / version
    python = venv / "bin" / "python"
    stamp = venv / ".installed"
    if stamp.is_file():
        return python
    subprocess.run([sys.executable, "-m", "venv", "--clear", str(venv)], check=True)
    # numpy < 2: the bpy builds of these series are compiled against numpy 1.x.
    result = subprocess.run([str(python), "-m", "pip", "install", "--quiet", f"bpy=={version}", "numpy<2"],
                            capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"pip install bpy=={version} into {venv} failed:\n{result.stdout[-2000:]}{result.stderr[-2000:]}")
    stamp.touch()
    return python


def bpy313_python(version: str) -> tuple[Path, Path]:
    """(the trixie chroot, the path inside it of a Python 3.13 with ``bpy==version``), made on
    first use; raises with the reason when the chroot or the venv cannot be made."""
    root = blender_gui.ensure_chroot("trixie")
    venv = Path("/opt/bpy") / version
    python = venv / "bin" / "python"
    stamp = root / venv.relative_to("/") / ".installed"
    if stamp.is_file():
        return root, python
    with blender_gui.mounted(root):
        for command in (["/usr/bin/python3", "-m", "venv", "--clear", str(venv)],
                        [str(python), "-m", "pip", "install", "--quiet", f"bpy=={version}"]):
            result = subprocess.run(["chroot", str(root), "/usr/bin/env", "-i", *CHROOT_ENV, "HOME=/root", *command],
                                    capture_output=True, text=True)
            if result.returncode != 0:
                raise RuntimeError(f"{' '.join(command)} in {root} failed:\n{result.stdout[-2000:]}{result.stderr[-2000:]}")
    stamp.touch()
    return root, python


def run_in_blender(version: str, script: Path, arguments: list[str], work: Path, extra_paths: tuple[Path, ...] = (),
                   env: dict[str, str] | None = None, timeout: float = 1500) -> subprocess.CompletedProcess:
    """``python SCRIPT ARGUMENTS`` in Blender ``version`` ("newest": the .venv's), with ``env``
    added to its environment and the backend's Python named in ``NERF_BACKEND_PYTHON`` where
    Blender's is not it. ``work`` and ``extra_paths`` are folders the script reads or writes:
    inside the chroot they are at the same paths."""
    env = env or {}
    if version == "newest":
        return subprocess.run([sys.executable, str(script), *arguments], cwd=REPO_ROOT, env={**os.environ, **env},
                              capture_output=True, text=True, timeout=timeout)
    if version not in PY313_VERSIONS:
        return subprocess.run([str(bpy_python(version)), str(script), *arguments], cwd=REPO_ROOT,
                              env={**os.environ, **env, "NERF_BACKEND_PYTHON": sys.executable},
                              capture_output=True, text=True, timeout=timeout)
    root, python = bpy313_python(version)
    # The backend as seen from the chroot: the project's .venv on the host, through /host.
    backend = work / "backend-python"
    backend.write_text(f'#!/bin/sh\nexec /usr/sbin/chroot /host /usr/bin/env -C "$PWD" "{sys.executable}" "$@"\n')
    backend.chmod(0o755)
    (work / "home").mkdir(exist_ok=True)
    folders = tuple(dict.fromkeys(p.resolve() for p in (work, REPO_ROOT, *extra_paths)))
    with blender_gui.mounted(root, folders, host=True):
        return subprocess.run(["chroot", str(root), "/usr/bin/env", "-i", *CHROOT_ENV, f"HOME={work / 'home'}",
                               f"NERF_BACKEND_PYTHON={backend}", *(f"{k}={v}" for k, v in env.items()),
                               "/usr/bin/env", "-C", str(REPO_ROOT),
                               str(python), str(script), *arguments],
                              capture_output=True, text=True, timeout=timeout)
