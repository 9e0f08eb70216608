"""What this machine can do, measured now: the yardsticks bench-step states each stage
against. Measured, not looked up: the same CPU model runs at other speeds on other machines
(and two kinds of CPU, with and without AVX-512, share this project's machines)."""

from __future__ import annotations

import ctypes
import time

import torch

from ..core.devices import synchronise
from ..kernels.build import load_kernel


LINE_FLOATS = 16  # float32 values in a 64-byte cache line


def _best_seconds(work, repeats: int) -> float:
    work()  # warm-up: allocation and first-touch costs are not the machine's rate
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        best = min(best, time.perf_counter() - start)
    return best


def measure_hardware(device: torch.device, repeats: int = 3, table_bytes: int = 64 * 2**20) -> dict:
    """FLOP rate (a 2048² float32 matrix product), copy bandwidth (read and write counted), and
    the rates of random single-float gathers and of random 64-byte cache lines (a grid row's
    read: 16 floats) from a table of ``table_bytes`` (give the field's size, since a table that
    fits in cache gathers faster), each the best of ``repeats``; on the CPU the lines are also
    read by a compiled loop with many in flight, and the faster rate counts.

    Example:
        >>> rates = measure_hardware(torch.device("cpu"), repeats=1)
        >>> sorted(rates), rates["gflops"] > 0
        (['bandwidth_gb_s', 'gathers_m_s', 'gflops', 'lines_m_s'], True)
    """
    def synchronised(work):
        def run():
            work()
            synchronise(device)
        return run

    a = torch.randn(2048, 2048, device=device)
    b = torch.randn(2048, 2048, device=device)
    matmul = _best_seconds(synchronised(lambda: a @ b), repeats)
    # The copy rate of 256 MB and of a table of the field's size, the faster of the two: work on a
    # working set that fits in a cache moves faster than memory does, and the reference must
    # stay a lower bound.
    bandwidths = []
    for floats in (64 * 2**20, max(table_bytes // 4, 2**18)):
        source = torch.empty(floats, device=device)
        target = torch.empty_like(source)
        copy = _best_seconds(synchronised(lambda: target.copy_(source)), repeats)
        bandwidths.append(2 * source.numel() * 4 / copy / 1e9)
    table = torch.randn(max(table_bytes // 4, 2**18), device=device)
    index = torch.randint(len(table), (8 * 2**20,), device=device)
    gather = _best_seconds(synchronised(lambda: table.index_select(0, index)), repeats)
    rows = table[:len(table) // LINE_FLOATS * LINE_FLOATS].view(-1, LINE_FLOATS)  # one cache line a row
    row_index = torch.randint(len(rows), (2**20,), device=device)
    lines = _best_seconds(synchronised(lambda: rows.index_select(0, row_index)), repeats)
    compiled = _compiled_lines_seconds(rows, row_index, repeats) if device.type == "cpu" else None
    return {"gflops": 2 * 2048**3 / matmul / 1e9, "bandwidth_gb_s": max(bandwidths),
            "gathers_m_s": index.numel() / gather / 1e6,
            "lines_m_s": row_index.numel() / min(lines, compiled or lines) / 1e6}


def _compiled_lines_seconds(rows: torch.Tensor, row_index: torch.Tensor, repeats: int) -> float | None:
    """The seconds ``kernels/machine_rates.c`` takes to read ``rows[row_index]`` on every
    thread with many lines in flight (as the compiled grid kernels read), or None without a C
    compiler. The faster of it and PyTorch's gather is the rate: a reference must stay a lower
    bound."""
    library = load_kernel("machine_rates")[0]
    if library is None:
        return None
    library.gather_lines.restype = ctypes.c_float
    table, index = rows.contiguous(), row_index.contiguous()
    arguments = (ctypes.c_void_p(table.data_ptr()), ctypes.c_void_p(index.data_ptr()), ctypes.c_int64(index.numel()),
                 ctypes.c_int64(torch.get_num_threads()))
    return _best_seconds(lambda: library.gather_lines(*arguments), repeats)
