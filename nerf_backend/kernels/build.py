"""Compiled CPU kernels: plain C sources beside this file, built on first use with the system's
C compiler into a per-user cache and loaded with ctypes.

Why this way and not a PyTorch C++ extension or ``torch.compile``: a plain C file needs only a C
compiler (no Python headers, no ninja, no PyTorch build tools), builds in about a second, and
a machine without a compiler (Windows without Visual Studio, say) still renders, through the
PyTorch path, which computes the same image (tests/test_compiled_march.py).

Example:
    >>> library, reason = load_kernel("march_render")
    >>> (library is None) == (reason is not None)
    True
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

SOURCES = Path(__file__).resolve().parent
# POSIX 2008 for clock_gettime (the worker pool's spin, grid_common.h) under strict C99.
FLAGS = ("-O3", "-std=c99", "-D_POSIX_C_SOURCE=200809L", "-shared", "-fPIC", "-pthread", "-fno-math-errno")
# Code for the running CPU (AVX-512 where it has it, AVX2 where not: this project's machines
# differ), keyed by the CPU's identity so a cache shared between machines never runs code the
# CPU lacks; a compiler that refuses the flag builds portable code. Tests also build for older
# instruction sets the CPU runs (``target``), to check the kernels' code for each vector width.
NATIVE_TARGET = "native"
# Another ``-march`` for every kernel a process loads, where set: x86-64-v3 runs the AVX2
# machines' code on an AVX-512 one (with torch's own AVX2 kernels, ATEN_CPU_CAPABILITY=avx2
# and ONEDNN_MAX_CPU_ISA=AVX2, docs/testing.md says how close that comes to an AVX2 machine).
TARGET_VARIABLE = "NERF_KERNEL_TARGET"
# Where built kernels are kept: NERF_KERNEL_CACHE, else the user's cache folder.
CACHE_VARIABLE = "NERF_KERNEL_CACHE"


def cache_folder() -> Path:
    named = os.environ.get(CACHE_VARIABLE)
    if named:
        return Path(named)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "nerf_backend" / "kernels"


def c_compiler() -> str | None:
    """``CC`` if set, else the first of cc, gcc, clang on the PATH."""
    named = os.environ.get("CC")
    if named:
        return shutil.which(named) or named
    return next((path for name in ("cc", "gcc", "clang") if (path := shutil.which(name))), None)


@functools.cache
def cpu_identity() -> str:
    """The CPU's model and instruction-set flags (Linux's /proc/cpuinfo), else what the
    platform says of the processor."""
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return platform.processor()
    wanted = ("model name", "flags", "Features", "CPU part")
    return "\n".join(sorted({line for line in text.splitlines() if line.split(":")[0].strip() in wanted}))


def load_kernel(name: str, target: str | None = None) -> tuple[ctypes.CDLL | None, str | None]:
    """The library built from ``NAME.c`` for the compiler's ``-march=TARGET`` (by default
    NERF_KERNEL_TARGET's, else the running CPU's) and None, or None and why it is unavailable
    (no compiler, a failed build); built once per source, compiler, target and machine, then
    reused."""
    return _load_kernel(name, target or os.environ.get(TARGET_VARIABLE) or NATIVE_TARGET)


@functools.cache
def _load_kernel(name: str, target: str) -> tuple[ctypes.CDLL | None, str | None]:
    source = SOURCES / f"{name}.c"
    compiler = c_compiler()
    if compiler is None:
        return None, "no C compiler (cc, gcc or clang) on the PATH; set CC to use another"
    try:  # the headers beside it too: a kernel may include them
        text = b"\0".join([source.read_bytes(), *(h.read_bytes() for h in sorted(SOURCES.glob("*.h")))])
    except OSError as exc:  # a partial install: the PyTorch path still runs
        return None, f"{source}: cannot be read ({exc.strerror or exc})"
    target_flags = (f"-march={target}",)
    key = hashlib.sha256(b"\0".join([text, compiler.encode(), " ".join(FLAGS + target_flags).encode(),
                                     platform.machine().encode(), platform.system().encode(),
                                     cpu_identity().encode()])).hexdigest()[:16]
    folder = cache_folder()
    library = folder / f"{name}-{key}.so"
    if not library.is_file():
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=folder) as scratch:
                built = Path(scratch) / library.name
                tries = ((*FLAGS, *target_flags), FLAGS) if target == NATIVE_TARGET else ((*FLAGS, *target_flags),)
                for flags in tries:
                    result = subprocess.run([compiler, *flags, str(source), "-o", str(built), "-lm"],
                                            capture_output=True, text=True, timeout=120, check=False)
                    if result.returncode == 0:
                        break
                if result.returncode != 0:
                    last = (result.stderr.strip().splitlines() or ["no message"])[-1]
                    return None, f"{compiler} could not build {source}: {last}"
                os.replace(built, library)  # atomic: a parallel process loads a whole file or builds its own
        except (OSError, subprocess.TimeoutExpired) as exc:
            return None, f"building {source} into {folder} failed: {exc}"
    try:
        return ctypes.CDLL(str(library)), None
    except OSError as exc:
        return None, f"{library}: cannot be loaded ({exc})"


_noted: set[str] = set()


def kernel_or_note(name: str, instead: str) -> tuple[ctypes.CDLL | None, str | None]:
    """``load_kernel(name)``; where it is unavailable, one line on stderr (once per kernel and
    process) says what runs ``instead`` and why."""
    library, reason = load_kernel(name)
    if library is None and name not in _noted:
        _noted.add(name)
        print(f"note: {instead}, not the compiled kernel: {reason}", file=sys.stderr)
    return library, reason
