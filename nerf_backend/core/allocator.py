"""The C library's allocator kept from handing large freed blocks back to the kernel.

glibc serves each block above its mmap threshold (at most 32 MB) with fresh pages from the
kernel and returns them when the block is freed; PyTorch's CPU tensors are such blocks. A render
chunk allocates its packed samples and its rays' composited features (about 19 MB at lego's 65 536
rays and 72 features) and frees them, ten chunks a view: every chunk's pages were zeroed by the
kernel on first touch again, 31 700 page faults and about 0.1 s of system time a view, 8 % of the
rendering's CPU time (docs/benchmarks_lego.md, session 68). With the threshold at glibc's largest
and the heap's freed top kept, the same blocks are reused: 24 faults a view.

Only on Linux with glibc (``mallopt``); elsewhere, and where the user sets glibc's own
``MALLOC_*_`` variables, nothing changes.
"""

from __future__ import annotations

import ctypes
import os
import sys

# glibc's malloc.h
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
SETTINGS = {
    M_MMAP_THRESHOLD: 32 << 20,  # glibc's largest: blocks below it come from the heap
    M_TRIM_THRESHOLD: 1 << 30,   # freed memory at the heap's top is kept up to this much
    M_TOP_PAD: 64 << 20,         # and the heap grows by at least this much at a time
}
USER_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")


def keep_freed_memory() -> bool:
    """Sets glibc's allocator as above for this process; True where it did."""
    if not sys.platform.startswith("linux") or any(name in os.environ for name in USER_VARIABLES):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return all([mallopt(parameter, value) == 1 for parameter, value in SETTINGS.items()])
