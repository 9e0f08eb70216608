"""The Blender versions users run, as ``bpy`` modules from PyPI, each in a virtual environment
of its own (one Python cannot hold two ``bpy`` versions).

The project's ``.venv`` holds the newest (requirements-dev.txt); the LTS releases are made
here on first use and kept in ``.venv-bpy/VERSION/`` (about 1 GB and a minute each). Their
Python runs Blender only: the add-on's backend is still the project's ``.venv``, as a
user's Blender would point at a separate Python that has torch."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
VENVS = REPO_ROOT / ".venv-bpy"

# The manifest's minimum series (4.2 LTS), the other LTS (4.5), and the newest (the .venv's).
# The newest patch release of each series on PyPI for Python 3.11.
LTS_VERSIONS = ("4.2.23", "4.5.15")


def bpy_python(version: str) -> Path:
    """A Python with ``bpy==version`` (made on first use); raises with pip's output on failure."""
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
