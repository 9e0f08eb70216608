"""Set Up Backend's choice of PyTorch build: a pure function of the platform and GPU facts,
found from recorded outputs of nvidia-smi and rocminfo; the pip commands it builds; the check
after installing. Nothing here downloads a CUDA build."""

from __future__ import annotations

import sys

import pytest

from addon.core.backend_setup import BackendSetup, describe_check, run_check
from addon.core.torch_builds import (INDEX, PlatformFacts, TorchBuild, choose_build, detect_facts, install_commands,
                                     parse_nvidia_smi, parse_rocminfo, torch_requirement)
from conftest import REPO_ROOT

# nvidia-smi's summary table as drivers print it (the header carries the newest CUDA the driver
# supports), and `nvidia-smi -L`.
NVIDIA_SMI_WINDOWS = """\
Tue Nov 24 10:12:31 2026
+-----------------------------------------------------------------------------------------+
| NVIDIA-SMI 560.94                 Driver Version: 560.94         CUDA Version: 12.6     |
|-----------------------------------------+------------------------+----------------------+
| GPU  Name                  Driver-Model | Bus-Id          Disp.A | Volatile Uncorr. ECC |
| Fan  Temp   Perf          Pwr:Usage/Cap |           Memory-Usage | GPU-Util  Compute M. |
|=========================================+========================+======================|
|   0  NVIDIA GeForce RTX 4070      WDDM  |   00000000:01:00.0  On |                  N/A |
|  0%   38C    P8              9W /  200W |    1024MiB /  12282MiB |      3%      Default |
+-----------------------------------------+------------------------+----------------------+
"""
NVIDIA_SMI_L_WINDOWS = "GPU 0: NVIDIA GeForce RTX 4070 (UUID: GPU-3f2a9c4e-1b7d-4e55-9a0c-2d8e6f1b7a90)\n"
NVIDIA_SMI_LINUX = """\
+-----------------------------------------------------------------------------------------+
| NVIDIA-SMI 580.95.05              Driver Version: 580.95.05      CUDA Version: 13.0     |
+-----------------------------------------+------------------------+----------------------+
|   0  NVIDIA H100 80GB HBM3          On  |   00000000:19:00.0 Off |                    0 |
+-----------------------------------------+------------------------+----------------------+
"""
NVIDIA_SMI_L_LINUX = "GPU 0: NVIDIA H100 80GB HBM3 (UUID: GPU-9d1e0b6a-58c3-4f0e-8d2b-7a6c5e4f3a21)\n"
NVIDIA_SMI_OLD_DRIVER = """\
| NVIDIA-SMI 470.256.02   Driver Version: 470.256.02   CUDA Version: 11.4     |
"""
ROCMINFO = """\
ROCk module version 6.8.5 is loaded
=====================
HSA System Attributes
=====================
Runtime Version:         1.14
==========
HSA Agents
==========
*******
Agent 1
*******
  Name:                    AMD Ryzen 9 7950X 16-Core Processor
  Marketing Name:          AMD Ryzen 9 7950X 16-Core Processor
  Device Type:             CPU
*******
Agent 2
*******
  Name:                    gfx1100
  Marketing Name:          AMD Radeon RX 7900 XTX
  Vendor Name:             AMD
  Device Type:             GPU
"""


def recorded(outputs: dict[str, str]):
    """A tool runner answering from recorded outputs (None: the tool is not installed)."""
    return lambda command: outputs.get(" ".join(command))


def test_nvidia_smi_and_rocminfo_outputs_parse():
    assert parse_nvidia_smi(NVIDIA_SMI_WINDOWS, NVIDIA_SMI_L_WINDOWS) == ("NVIDIA GeForce RTX 4070", "560.94", (12, 6))
    assert parse_nvidia_smi(NVIDIA_SMI_LINUX, NVIDIA_SMI_L_LINUX) == ("NVIDIA H100 80GB HBM3", "580.95.05", (13, 0))
    assert parse_nvidia_smi("garbage", "") == (None, None, None)
    assert parse_rocminfo(ROCMINFO) == "AMD Radeon RX 7900 XTX (gfx1100)"
    assert parse_rocminfo(ROCMINFO.replace("Device Type:             GPU", "Device Type:             CPU")) is None


# The table in the README ("Which PyTorch Set Up Backend installs"): platform and tools' outputs
# → build key, device, index.
CASES = [
    ("Windows, RTX 4070, driver for CUDA 12.6", "Windows", "AMD64",
     {"nvidia-smi": NVIDIA_SMI_WINDOWS, "nvidia-smi -L": NVIDIA_SMI_L_WINDOWS}, "cu126", "cuda"),
    ("Windows, driver for CUDA 12.8", "Windows", "AMD64",
     {"nvidia-smi": NVIDIA_SMI_WINDOWS.replace("12.6", "12.8"), "nvidia-smi -L": NVIDIA_SMI_L_WINDOWS}, "cu128", "cuda"),
    ("Windows, no NVIDIA GPU", "Windows", "AMD64", {}, "cpu", "cpu"),
    ("Windows, NVIDIA driver too old (CUDA 11.4)", "Windows", "AMD64",
     {"nvidia-smi": NVIDIA_SMI_OLD_DRIVER, "nvidia-smi -L": NVIDIA_SMI_L_WINDOWS}, "cpu", "cpu"),
    ("Linux, H100, driver for CUDA 13.0", "Linux", "x86_64",
     {"nvidia-smi": NVIDIA_SMI_LINUX, "nvidia-smi -L": NVIDIA_SMI_L_LINUX}, "cu130", "cuda"),
    ("Linux, AMD GPU with ROCm's tools", "Linux", "x86_64", {"rocminfo": ROCMINFO}, "rocm6.4", "rocm"),
    ("Linux, no GPU", "Linux", "x86_64", {}, "cpu", "cpu"),
    ("macOS, Apple silicon", "Darwin", "arm64", {}, "macos", "mps"),
    ("macOS, Intel", "Darwin", "x86_64", {}, "none", "none"),
]


@pytest.mark.parametrize("label, system, machine, outputs, key, device", CASES, ids=[case[0] for case in CASES])
def test_the_build_follows_the_platform_and_gpu(label, system, machine, outputs, key, device, tmp_path, monkeypatch):
    monkeypatch.setattr("addon.core.torch_builds._amd_gpu_in_sysfs", lambda drm=None: None)
    build = choose_build(detect_facts(system, machine, run=recorded(outputs)))
    assert (build.key, build.device) == (key, device), build.reason
    if device in {"cuda", "rocm", "cpu"}:
        assert build.index_url == f"{INDEX}{key}"  # never PyPI's torch, which is CUDA on Linux, CPU elsewhere
    else:
        assert build.index_url is None
    assert build.reason and build.download


def test_reasons_say_what_to_do():
    old = choose_build(PlatformFacts("Windows", "AMD64", "NVIDIA GeForce GTX 1060", "470.256.02", (11, 4)))
    assert "CUDA 11.4" in old.reason and "update the NVIDIA driver" in old.reason
    intel_mac = choose_build(PlatformFacts("Darwin", "x86_64"))
    assert "Backend Python" in intel_mac.reason
    windows_amd = choose_build(PlatformFacts("Windows", "AMD64", amd_gpu="AMD Radeon RX 7900 XTX"))
    assert windows_amd.key == "cpu" and "Linux only" in windows_amd.reason
    assert choose_build(PlatformFacts("Linux", "x86_64")).describe() == "PyTorch, CPU only build (about 0.2 GB)"
    assert choose_build(PlatformFacts("Linux", "x86_64", "H100", "580", (13, 0))).describe() == \
        "PyTorch, CUDA 13.0 build (about 3.5 GB)"


def test_the_preferences_override_the_detected_choice():
    gpu = PlatformFacts("Linux", "x86_64", "NVIDIA H100 80GB HBM3", "580.95.05", (13, 0))
    assert choose_build(gpu, "cpu").key == "cpu"
    forced = choose_build(PlatformFacts("Linux", "x86_64"), "cu128")
    assert (forced.key, forced.device, forced.index_url) == ("cu128", "cuda", INDEX + "cu128")
    with pytest.raises(ValueError, match="unknown PyTorch build 'cu999'"):
        choose_build(gpu, "cu999")


def test_an_amd_gpu_is_found_in_sysfs_without_rocm_tools(tmp_path):
    from addon.core.torch_builds import _amd_gpu_in_sysfs

    (tmp_path / "card0" / "device").mkdir(parents=True)
    (tmp_path / "card0" / "device" / "vendor").write_text("0x8086\n")  # Intel graphics
    assert _amd_gpu_in_sysfs(tmp_path) is None
    (tmp_path / "card1" / "device").mkdir(parents=True)
    (tmp_path / "card1" / "device" / "vendor").write_text("0x1002\n")
    assert _amd_gpu_in_sysfs(tmp_path) == "AMD GPU"


def test_pip_installs_torch_from_the_builds_index_then_the_rest():
    requirements = REPO_ROOT / "nerf_backend" / "requirements.txt"
    assert torch_requirement(requirements) == "torch>=2.4"
    build = choose_build(PlatformFacts("Windows", "AMD64", "RTX 4070", "560.94", (12, 6)))
    pip = ["py", "-m", "pip", "install", "--progress-bar", "off", "--no-compile"]
    no_deps = pip + ["--no-deps", "-r", str(requirements.with_name("requirements-no-deps.txt"))]
    assert install_commands("py", build, requirements) == [
        pip + ["--index-url", "https://download.pytorch.org/whl/cu126", "torch>=2.4"],
        pip + ["-r", str(requirements)], no_deps]
    mac = choose_build(PlatformFacts("Darwin", "arm64"))
    assert install_commands("py", mac, requirements) == [pip + ["-r", str(requirements)], no_deps]


def test_the_check_tells_a_cpu_build_from_an_unusable_gpu():
    facts, problem = run_check(sys.executable)  # this project's torch: the CPU build
    assert facts is not None, problem
    assert facts["cuda"] is False and facts["cuda_build"] is None
    assert describe_check(facts, "cpu") == (True, f"torch {facts['torch']}, CPU only")
    usable, line = describe_check(facts, "cuda")
    assert not usable and "CPU-only build" in line
    # A CUDA build whose driver is too old: is_available() False (recorded facts).
    old_driver = dict(facts, torch="2.9.0+cu130", cuda_build="13.0", gpu_error="torch.cuda.is_available() is False")
    usable, line = describe_check(old_driver, "cuda")
    assert not usable and "CUDA 13.0 build but cannot use the GPU" in line and "driver" in line
    assert describe_check(dict(facts, cuda=True, gpu="NVIDIA H100"), "cuda") == (True, f"torch {facts['torch']}, GPU NVIDIA H100")


def test_setup_refuses_a_platform_without_a_build(tmp_path):
    build = choose_build(PlatformFacts("Darwin", "x86_64"))
    setup = BackendSetup(tmp_path / "venv", sys.executable, REPO_ROOT / "nerf_backend" / "requirements.txt", build)
    with pytest.raises(RuntimeError, match="Intel Macs"):
        setup.start()
    assert not (tmp_path / "venv").exists()


def test_setup_fails_clearly_when_the_builds_index_has_no_torch(tmp_path, monkeypatch):
    """A real pip against a real (empty) package index: the error names the index and torch.
    This machine's pip settings (a folder of wheels holding torch) are left out."""
    monkeypatch.setenv("PIP_CONFIG_FILE", "/dev/null")
    monkeypatch.delenv("PIP_FIND_LINKS", raising=False)
    index = tmp_path / "index"
    index.mkdir()
    (index / "index.html").write_text("<html><body></body></html>\n")
    build = TorchBuild("cpu", index.as_uri(), "cpu", "about 0.2 GB", "test")
    setup = BackendSetup(tmp_path / "venv", sys.executable, REPO_ROOT / "nerf_backend" / "requirements.txt", build)
    setup.start()
    setup.wait(600)
    status = setup.poll()
    assert status.state == "failed"
    assert status.error.startswith("installing the backend's packages")
    assert f"--index-url {index.as_uri()} torch>=2.4 failed" in status.error
    assert "No matching distribution found for torch" in status.error  # pip's own words, kept
