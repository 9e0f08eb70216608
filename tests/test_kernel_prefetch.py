"""The grid kernel's prefetches reach the machine code.

``__builtin_prefetch`` is a hint without side effects, so a compiler may drop it. GCC 12 did
for every call of vm_grid.c's ``prefetch_rows`` (a helper of prefetches alone, found "looping
pure", its calls removed at -O1 and above) until it was always inlined: the forward, the
backward, the lit pass's backward and the colour pass asked memory for nothing ahead, while
their comments said they did. The kernel is compiled here to assembly with the flags
``build.py`` uses, and each function that asks for rows ahead must hold a prefetch
instruction."""

from __future__ import annotations

import platform
import re
import subprocess

import pytest
from conftest import cpu_runs_x86_level

from nerf_backend.kernels.build import FLAGS, NATIVE_TARGET, SOURCES, c_compiler

# The worker functions of vm_grid.c (and the headers it includes) that call prefetch_rows or
# density_prefetch: forward_work and backward_work (vm_grid.c), lit_grids_backward_work
# (lit_pass.h), colour_work (colour_network.h), train_march_work (train_march.h).
ASKING_AHEAD = ("forward_work", "backward_work", "lit_forward_work", "lit_grids_backward_work", "colour_work", "train_march_work")
PREFETCH = re.compile(r"^\s+(prefetch\w*|prfm)\b", re.MULTILINE)  # x86's prefetcht0/prefetchw, ARM's prfm
LABEL = re.compile(r"^_?([A-Za-z_]\w*)(?:\.\w+)*:", re.MULTILINE)  # a function and its .cold/.part pieces


def _functions(assembly: str) -> dict[str, str]:
    """Each function's text in ``assembly`` (its pieces joined), by name."""
    bodies: dict[str, str] = {}
    labels = list(LABEL.finditer(assembly))
    for label, following in zip(labels, labels[1:] + [None]):
        end = following.start() if following else len(assembly)
        bodies[label.group(1)] = bodies.get(label.group(1), "") + assembly[label.end():end]
    return bodies


def _assembly(target: str) -> str:
    compiler = c_compiler()
    if compiler is None:
        pytest.skip("no C compiler: the kernels are not built here")
    flags = [flag for flag in FLAGS if flag != "-shared"]
    # As build.py: a compiler that refuses -march=native builds portable code.
    tries = ([f"-march={target}"], []) if target == NATIVE_TARGET else ([f"-march={target}"],)
    for target_flags in tries:
        result = subprocess.run([compiler, *flags, *target_flags, "-S", str(SOURCES / "vm_grid.c"), "-o", "-"],
                                capture_output=True, text=True, timeout=120, check=False)
        if result.returncode == 0:
            return result.stdout
    raise AssertionError(result.stderr[-2000:])


@pytest.mark.parametrize("target", [NATIVE_TARGET, "x86-64-v3"])
def test_every_function_that_asks_for_rows_ahead_holds_a_prefetch_instruction(target):
    if target != NATIVE_TARGET and not (platform.machine() in ("x86_64", "AMD64") and cpu_runs_x86_level(target)):
        pytest.skip(f"{target}: not this machine's code")
    functions = _functions(_assembly(target))
    missing = [name for name in ASKING_AHEAD if name in functions and not PREFETCH.search(functions[name])]
    absent = [name for name in ASKING_AHEAD if name not in functions]
    assert not absent, f"not in the assembly (renamed? inlined?): {absent}"
    assert not missing, f"the compiler dropped their prefetches: {missing}"
