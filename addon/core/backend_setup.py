"""The backend's own Python: Blender's bundled Python has no torch, so training runs in a
virtual environment the add-on creates ("Set Up Backend") or in any interpreter the user
names in the preferences. Plain Python, no bpy: a thread does the work, the panel polls.
Which PyTorch build it installs is ``torch_builds``' choice.
"""

from __future__ import annotations

import json
import os
import subprocess
import threading
from pathlib import Path

from .jobs import JobStatus, python_in_venv
from .torch_builds import TorchBuild, install_commands

# Printed by the backend's Python: one line of JSON. The small kernel proves that the GPU runs
# work, which is_available() alone does not (a driver too old for the build fails only there).
CHECK_SCRIPT = """
import json, torch, numpy, PIL, imageio, tqdm, matplotlib, OpenEXR
facts = {"torch": torch.__version__, "cuda_build": torch.version.cuda,
         "hip_build": getattr(torch.version, "hip", None), "cuda": False, "gpu": None, "gpu_error": None}
mps = getattr(torch.backends, "mps", None)
facts["mps"] = bool(mps and mps.is_available())
try:
    if torch.cuda.is_available():
        x = torch.arange(1024, device="cuda", dtype=torch.float32)
        facts["cuda"] = float((x * 2).sum().item()) == 1047552.0
        facts["gpu"] = torch.cuda.get_device_name(0)
    elif facts["cuda_build"] or facts["hip_build"]:
        facts["gpu_error"] = "torch.cuda.is_available() is False"
except Exception as exc:
    facts["gpu_error"] = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
print(json.dumps(facts))
"""


# Run by the new backend (PYTHONPATH: the source root): LPIPS's AlexNet weights into torch hub's
# cache, so the first comparison does not wait for them; offline it says why, and setup goes on.
FETCH_LPIPS_SCRIPT = """
from nerf_backend.metrics.lpips_metric import LpipsUnavailable, fetch_backbone
try:
    print("LPIPS weights: " + str(fetch_backbone(progress=False)))
except LpipsUnavailable as exc:
    print("LPIPS unavailable: " + str(exc))
"""


def describe_check(facts: dict, expected: str | None = None) -> tuple[bool, str]:
    """(the GPU is usable as ``expected``, a line for the panel) from CHECK_SCRIPT's output.
    ``expected`` is the chosen build's device (cuda, rocm, mps, cpu), None when the Python was
    not set up here.

    >>> describe_check({"torch": "2.9.0+cpu", "cuda_build": None, "cuda": False, "mps": False}, "cuda")
    (False, 'torch 2.9.0+cpu, CPU only: this torch is a CPU-only build, though a CUDA build was chosen')
    """
    device = f"GPU {facts['gpu']}" if facts.get("cuda") else "Apple GPU (MPS)" if facts.get("mps") else "CPU only"
    line = f"torch {facts['torch']}, {device}"
    if expected in {"cuda", "rocm"} and not facts.get("cuda"):
        if not (facts.get("cuda_build") or facts.get("hip_build")):
            return False, f"{line}: this torch is a CPU-only build, though a {expected.upper()} build was chosen"
        build = f"CUDA {facts['cuda_build']}" if facts.get("cuda_build") else f"ROCm {facts['hip_build']}"
        return False, (f"{line}: torch is a {build} build but cannot use the GPU ({facts.get('gpu_error')}); "
                       "the driver may be too old for it: update the driver, or choose another build in the preferences")
    if expected == "mps" and not facts.get("mps"):
        return False, f"{line}: MPS is not available (it needs macOS 12.3 or newer on Apple silicon)"
    return True, line


def run_check(python: str, timeout: float = 120) -> tuple[dict | None, str]:
    """CHECK_SCRIPT's facts from ``python``, or None and why it could not run."""
    if not python or not Path(python).is_file():
        return None, f"no Python at {python or '(not set)'}: set one in the preferences or press Set Up Backend"
    try:
        result = subprocess.run([python, "-c", CHECK_SCRIPT], capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return None, f"{python} could not run: {exc}"
    if result.returncode != 0:
        last = (result.stderr.strip().splitlines() or ["no output"])[-1]
        return None, f"{python} lacks the backend's packages ({last}); press Set Up Backend"
    return json.loads(result.stdout.strip().splitlines()[-1]), ""


def check_backend(python: str, timeout: float = 120) -> tuple[bool, str]:
    """Whether ``python`` can run the backend, and a line saying what it has (or lacks)."""
    facts, problem = run_check(python, timeout)
    if facts is None:
        return False, problem
    return True, describe_check(facts)[1]


class BackendSetup:
    """Create ``venv`` from ``base_python`` and pip-install ``build`` of PyTorch and the rest of
    ``requirements`` into it, in a thread. ``poll()`` reports the step and the package pip is
    on; a failure keeps pip's last lines as the error. A GPU build whose GPU the check cannot
    use ends "done" with a warning that says why (training still runs on the CPU)."""

    STEPS = ("creating the virtual environment", "installing the backend's packages", "checking the backend",
             "fetching LPIPS's AlexNet weights")

    def __init__(self, venv: Path, base_python: str, requirements: Path, build: TorchBuild,
                 backend_root: Path | None = None) -> None:
        self.venv, self.base_python, self.requirements = Path(venv), base_python, Path(requirements)
        self.build, self.backend_root = build, backend_root  # backend_root: where nerf_backend is (LPIPS's step)
        self._step = 0
        self._line = ""
        self._lines: list[str] = []
        self._state = "idle"
        self._message = ""
        self._warning = ""
        self._thread: threading.Thread | None = None

    @property
    def python(self) -> Path:
        return python_in_venv(self.venv)

    def start(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("the backend is already being set up")
        if not self.requirements.is_file():
            raise FileNotFoundError(f"{self.requirements}: the backend's requirements file is missing")
        if self.build.device == "none":
            raise RuntimeError(self.build.reason)
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
            raise RuntimeError(f"{' '.join(command[1:])} failed (exit code {process.returncode})")

    def _work(self) -> None:
        try:
            self._step = 0
            if not self.python.is_file():
                self._run([self.base_python, "-m", "venv", str(self.venv)])
            self._step = 1
            for command in install_commands(str(self.python), self.build, self.requirements):
                self._run(command)
            self._step = 2
            facts, problem = run_check(str(self.python))
            if facts is None:
                raise RuntimeError(problem)
            usable, message = describe_check(facts, self.build.device)
            self._warning = "" if usable else message  # a GPU it cannot use: shown, not fatal
            if self.backend_root is not None:
                self._step = 3
                message += "; " + self._fetch_lpips()
            self._state, self._message = "done", message
        except Exception as exc:  # reported to the panel with pip's last lines
            self._state = "failed"
            self._message = f"{self.STEPS[self._step]}: {exc}\n" + "\n".join(self._lines[-8:])

    def _fetch_lpips(self) -> str:
        """The LPIPS step's one line (never fatal: LPIPS is reported unavailable without it)."""
        try:
            result = subprocess.run([str(self.python), "-c", FETCH_LPIPS_SCRIPT], capture_output=True, text=True,
                                    timeout=3600, env=dict(os.environ, PYTHONPATH=str(self.backend_root)))
        except (OSError, subprocess.TimeoutExpired) as exc:
            return f"LPIPS unavailable: {exc}"
        lines = (result.stdout.strip() or result.stderr.strip() or "no output").splitlines()
        return lines[-1] if result.returncode == 0 else f"LPIPS unavailable: {lines[-1]}"

    def poll(self) -> JobStatus:
        if self._state == "running":
            return JobStatus("running", self._step / len(self.STEPS), f"{self.STEPS[self._step]}: {self._line}".rstrip(": "))
        if self._state == "failed":
            return JobStatus("failed", error=self._message)
        return JobStatus(self._state, 1.0 if self._state == "done" else 0.0, self._message, warning=self._warning)
