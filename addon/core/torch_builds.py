"""Which PyTorch build Set Up Backend installs: a pure function of the platform and GPU facts,
the tools that find those facts, and the pip commands that install the choice. No bpy.

PyPI's torch is a CPU build on Windows and macOS and a CUDA build of several GB on Linux, even
where no NVIDIA GPU is. PyTorch publishes each build on an index of its own
(https://download.pytorch.org/whl/<build>), so the choice is an index:

>>> facts = PlatformFacts("Windows", "AMD64", nvidia_gpu="NVIDIA GeForce RTX 4070",
...                       nvidia_driver="560.94", nvidia_cuda=(12, 6))
>>> build = choose_build(facts)
>>> build.key, build.device
('cu126', 'cuda')
>>> build.index_url
'https://download.pytorch.org/whl/cu126'
>>> choose_build(PlatformFacts("Linux", "x86_64")).key
'cpu'
"""

from __future__ import annotations

import platform
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

INDEX = "https://download.pytorch.org/whl/"

# PyTorch's CUDA builds as published for torch 2.9, newest first, with the CUDA version each needs
# the driver to support; update with each torch release that adds or drops one.
CUDA_BUILDS = (("cu130", (13, 0)), ("cu128", (12, 8)), ("cu126", (12, 6)))
ROCM_BUILD = "rocm6.4"

# Rough download sizes of torch and the packages it pulls, for the panel to say before it starts
# (PyTorch's indexes for torch 2.8-2.9, rounded; the Linux CPU figure is the 2.13.0 wheel's
# 192 MB). Linux CUDA builds pull NVIDIA's libraries as separate wheels; Windows' is one wheel.
DOWNLOAD_SIZES = {
    ("Linux", "cuda"): "about 3.5 GB", ("Windows", "cuda"): "about 3 GB",
    ("Linux", "rocm"): "about 5 GB",
    ("Linux", "cpu"): "about 0.2 GB", ("Windows", "cpu"): "about 0.2 GB",
    ("Darwin", "mps"): "about 0.1 GB",
}

# What the preferences may force instead of the detected choice.
OVERRIDES = ("auto", "cpu") + tuple(key for key, _ in CUDA_BUILDS) + (ROCM_BUILD,)


@dataclass(frozen=True)
class PlatformFacts:
    """What the choice depends on: ``platform.system()`` and ``platform.machine()``, the NVIDIA
    GPU and the newest CUDA its driver supports (from ``nvidia-smi``), and an AMD GPU (Linux)."""

    system: str
    machine: str
    nvidia_gpu: str | None = None
    nvidia_driver: str | None = None
    nvidia_cuda: tuple[int, int] | None = None
    amd_gpu: str | None = None


@dataclass(frozen=True)
class TorchBuild:
    """A PyTorch build: ``index_url`` None means PyPI's own. ``device`` is what it will train on
    (cuda, rocm, mps, cpu); ``reason`` says why it was chosen, for the panel."""

    key: str
    index_url: str | None
    device: str
    download: str
    reason: str

    def describe(self) -> str:
        names = {"cuda": f"CUDA {self.key[2:-1]}.{self.key[-1]}", "rocm": f"ROCm {self.key[4:]}",
                 "mps": "Apple GPU (MPS)", "cpu": "CPU only"}
        return f"PyTorch, {names.get(self.device, self.key)} build ({self.download})"


def _build(key: str, system: str, reason: str) -> TorchBuild:
    device = "cuda" if key.startswith("cu") else "rocm" if key.startswith("rocm") else key
    size = DOWNLOAD_SIZES.get((system, device), "size unknown")
    return TorchBuild(key, INDEX + key, device, size, reason)


def _cuda_build_for(cuda: tuple[int, int]) -> str | None:
    """The newest CUDA build a driver supporting CUDA ``cuda`` can run."""
    return next((key for key, needs in CUDA_BUILDS if needs <= cuda), None)


def choose_build(facts: PlatformFacts, override: str = "auto") -> TorchBuild:
    """The build for ``facts`` (see the module's table in the README), or the one ``override``
    names (a key of ``OVERRIDES``)."""
    system = facts.system
    if override not in OVERRIDES:
        raise ValueError(f"unknown PyTorch build {override!r}: choose one of {', '.join(OVERRIDES)}")
    if override != "auto":
        return _build(override, system, "chosen in the preferences")
    if system == "Darwin":
        if facts.machine.lower() in {"arm64", "aarch64"}:
            return TorchBuild("macos", None, "mps", DOWNLOAD_SIZES[("Darwin", "mps")],
                              "Apple silicon: PyPI's build trains on the GPU through MPS")
        return TorchBuild("none", None, "none", "nothing",
                          "Intel Macs: PyTorch publishes no build newer than 2.2 for them, and the backend needs "
                          "2.4; set the Backend Python in the preferences to a Python that has torch")
    if facts.nvidia_gpu and system in {"Windows", "Linux"}:
        gpu = f"{facts.nvidia_gpu} (driver {facts.nvidia_driver or '?'})"
        if facts.nvidia_cuda is None:
            return _build("cpu", system, f"{gpu}: nvidia-smi did not say which CUDA its driver supports, so the CPU "
                                         "build; choose a CUDA build in the preferences to try one")
        cuda = ".".join(map(str, facts.nvidia_cuda))
        key = _cuda_build_for(facts.nvidia_cuda)
        if key is None:
            oldest = ".".join(map(str, CUDA_BUILDS[-1][1]))
            return _build("cpu", system, f"{gpu} supports CUDA {cuda}, older than PyTorch's oldest build (CUDA "
                                         f"{oldest}): update the NVIDIA driver for GPU training; the CPU build until then")
        return _build(key, system, f"{gpu}, whose driver supports CUDA {cuda}")
    if facts.amd_gpu:
        if system == "Linux":
            return _build(ROCM_BUILD, system, f"{facts.amd_gpu}: PyTorch's ROCm build brings ROCm's libraries and "
                                              "needs the amdgpu kernel driver")
        return _build("cpu", system, f"{facts.amd_gpu}: PyTorch publishes ROCm builds for Linux only")
    return _build("cpu", system, "no NVIDIA or AMD GPU found: the CPU build, a fraction of the CUDA one's size")


# --- finding the facts -------------------------------------------------------------------------

def parse_nvidia_smi(summary: str, listing: str) -> tuple[str | None, str | None, tuple[int, int] | None]:
    """(GPU name, driver version, newest CUDA the driver supports) from ``nvidia-smi``'s summary
    table and ``nvidia-smi -L``'s list; Nones where a value is missing."""
    driver = re.search(r"Driver Version:\s*([0-9.]+)", summary)
    cuda = re.search(r"CUDA Version:\s*(\d+)\.(\d+)", summary)
    name = re.search(r"^GPU \d+:\s*(.+?)\s*(?:\(UUID|$)", listing, re.MULTILINE)
    return (name.group(1) if name else None, driver.group(1) if driver else None,
            (int(cuda.group(1)), int(cuda.group(2))) if cuda else None)


def parse_rocminfo(text: str) -> str | None:
    """The first GPU agent's marketing name and architecture from ``rocminfo``, e.g.
    'AMD Radeon RX 7900 XTX (gfx1100)'; None where it lists no GPU."""
    for agent in re.split(r"\*{5,}\s*\nAgent \d+", text)[1:]:
        if re.search(r"Device Type:\s*GPU", agent):
            marketing = re.search(r"Marketing Name:\s*(.+)", agent)
            arch = re.search(r"^\s*Name:\s*(gfx\w+)", agent, re.MULTILINE)
            name = marketing.group(1).strip() if marketing else "AMD GPU"
            return f"{name} ({arch.group(1)})" if arch else name
    return None


AMD_PCI_VENDOR = "0x1002"


def _amd_gpu_in_sysfs(drm: Path = Path("/sys/class/drm")) -> str | None:
    """An AMD display device in Linux's sysfs (where ROCm's tools are not installed)."""
    for vendor in sorted(drm.glob("card*/device/vendor")):
        try:
            if vendor.read_text().strip() == AMD_PCI_VENDOR:
                return "AMD GPU"
        except OSError:
            continue
    return None


Runner = Callable[[list[str]], str | None]


def run_tool(command: list[str], timeout: float = 10) -> str | None:
    """A tool's output, or None where it is missing or fails."""
    try:
        # CREATE_NO_WINDOW: on Windows a console would flash up while Blender draws the panel.
        result = subprocess.run(command, capture_output=True, text=True, timeout=timeout,
                                creationflags=getattr(subprocess, "CREATE_NO_WINDOW", 0))
    except (OSError, subprocess.TimeoutExpired):
        return None
    return result.stdout if result.returncode == 0 else None


def detect_facts(system: str | None = None, machine: str | None = None, run: Runner = run_tool) -> PlatformFacts:
    """The facts of this machine (``run`` is replaced in tests by recorded outputs)."""
    system = system or platform.system()
    machine = machine or platform.machine()
    name = driver = cuda = None
    summary = run(["nvidia-smi"])
    if summary is not None:
        name, driver, cuda = parse_nvidia_smi(summary, run(["nvidia-smi", "-L"]) or "")
        name = name or "NVIDIA GPU"
    amd = None
    if system == "Linux" and name is None:
        listing = run(["rocminfo"])
        amd = parse_rocminfo(listing) if listing else None
        amd = amd or _amd_gpu_in_sysfs()
    return PlatformFacts(system, machine, name, driver, cuda, amd)


# --- installing it -----------------------------------------------------------------------------

def torch_requirement(requirements: Path) -> str:
    """The torch line of the backend's requirements file (its one definition)."""
    for line in Path(requirements).read_text().splitlines():
        line = line.split("#")[0].strip()
        if re.match(r"torch\b(?![-_\w])", line):
            return line
    raise ValueError(f"{requirements}: no torch requirement in it")


def no_deps_requirements(requirements: Path) -> Path:
    """The file beside ``requirements`` of packages installed without their dependencies."""
    return Path(requirements).with_name("requirements-no-deps.txt")


def install_commands(python: str, build: TorchBuild, requirements: Path) -> list[list[str]]:
    """pip commands for ``build``: torch from its own index first (so PyPI's build is never
    taken), then the rest of ``requirements`` from PyPI, where torch is then already met, then
    the packages wanted without their dependencies.

    ``--no-compile``: pip byte-compiles every module it installs (torch's and its dependencies'
    tens of thousands of files: 25 of the 42 s of a CPU install from pip's cache), though the
    backend imports a few hundred of them. Python writes those on their first import instead,
    into the venv's own folders (the check after the install imports torch, 3 s once)."""
    pip = [str(python), "-m", "pip", "install", "--progress-bar", "off", "--no-compile"]
    commands = []
    if build.index_url is not None:
        commands.append(pip + ["--index-url", build.index_url, torch_requirement(requirements)])
    commands.append(pip + ["-r", str(requirements)])
    if no_deps_requirements(requirements).is_file():
        commands.append(pip + ["--no-deps", "-r", str(no_deps_requirements(requirements))])
    return commands
