"""The backend's own Python: Blender's bundled Python has no torch, so training runs in a
virtual environment the add-on creates ("Set Up Backend") or in any interpreter the user
names in the preferences. Plain Python, no bpy: a thread does the work, the panel polls.
"""

from __future__ import annotations

import os
import subprocess
import threading
from pathlib import Path

from .jobs import JobStatus, python_in_venv

# Printed by the check: one line of JSON.
CHECK_SCRIPT = (
    "import json, torch, numpy, PIL, imageio, tqdm, matplotlib, OpenEXR; "
    "mps = getattr(torch.backends, 'mps', None); "
    "print(json.dumps({'torch': torch.__version__, 'cuda': torch.cuda.is_available(), "
    "'mps': bool(mps and mps.is_available())}))"
)


def check_backend(python: str, timeout: float = 120) -> tuple[bool, str]:
    """Whether ``python`` can run the backend, and a line saying what it has (or lacks)."""
    import json

    if not python or not Path(python).is_file():
        return False, f"no Python at {python or '(not set)'}: set one in the preferences or press Set Up Backend"
    try:
        result = subprocess.run([python, "-c", CHECK_SCRIPT], capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return False, f"{python} could not run: {exc}"
    if result.returncode != 0:
        last = (result.stderr.strip().splitlines() or ["no output"])[-1]
        return False, f"{python} lacks the backend's packages ({last}); press Set Up Backend"
    facts = json.loads(result.stdout.strip().splitlines()[-1])
    device = "CUDA GPU" if facts["cuda"] else ("Apple GPU (MPS)" if facts["mps"] else "CPU only")
    return True, f"torch {facts['torch']}, {device}"


class BackendSetup:
    """Create ``venv`` from ``base_python`` and pip-install ``requirements`` into it, in a
    thread. ``poll()`` reports the step and the package pip is on; a failure keeps pip's
    last lines as the error."""

    STEPS = ("creating the virtual environment", "installing the backend's packages", "checking the backend")

    def __init__(self, venv: Path, base_python: str, requirements: Path) -> None:
        self.venv, self.base_python, self.requirements = Path(venv), base_python, Path(requirements)
        self._step = 0
        self._line = ""
        self._lines: list[str] = []
        self._state = "idle"
        self._message = ""
        self._thread: threading.Thread | None = None

    @property
    def python(self) -> Path:
        return python_in_venv(self.venv)

    def start(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("the backend is already being set up")
        if not self.requirements.is_file():
            raise FileNotFoundError(f"{self.requirements}: the backend's requirements file is missing")
        self._state = "running"
        self._thread = threading.Thread(target=self._work, daemon=True)
        self._thread.start()

    def wait(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self, command: list[str]) -> None:
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                   env=dict(os.environ, PIP_DISABLE_PIP_VERSION_CHECK="1"))
        for line in process.stdout:
            line = line.rstrip()
            if line:
                self._lines = (self._lines + [line])[-20:]
                if line.startswith(("Collecting", "Downloading", "Installing", "Successfully", "Requirement")):
                    self._line = line[:120]
        if process.wait() != 0:
            raise RuntimeError(f"{' '.join(command[:4])} ... failed (exit code {process.returncode})")

    def _work(self) -> None:
        try:
            self._step = 0
            if not self.python.is_file():
                self._run([self.base_python, "-m", "venv", str(self.venv)])
            self._step = 1
            self._run([str(self.python), "-m", "pip", "install", "--progress-bar", "off", "-r", str(self.requirements)])
            self._step = 2
            ok, message = check_backend(str(self.python))
            if not ok:
                raise RuntimeError(message)
            self._state, self._message = "done", message
        except Exception as exc:  # reported to the panel with pip's last lines
            self._state = "failed"
            self._message = f"{self.STEPS[self._step]}: {exc}\n" + "\n".join(self._lines[-8:])

    def poll(self) -> JobStatus:
        if self._state == "running":
            return JobStatus("running", self._step / len(self.STEPS), f"{self.STEPS[self._step]}: {self._line}".rstrip(": "))
        if self._state == "failed":
            return JobStatus("failed", error=self._message)
        return JobStatus(self._state, 1.0 if self._state == "done" else 0.0, self._message)
