"""The compiled kernels' kept workers (grid_common.h's run_all): the same results as the first
thread alone, whatever the thread count from call to call (more workers than cores, most of
them without an item in a job), with two callers at once (one gets new threads), after the
workers fell asleep, and in a forked child (which has no workers)."""

from __future__ import annotations

import multiprocessing
import threading
import time

import pytest
import torch

from nerf_backend.field_components import compiled_grid
from nerf_backend.field_components.grid_encodings import VectorMatrixGrid


@pytest.fixture(scope="module", autouse=True)
def library():
    found = compiled_grid.compiled_grid_library()
    if found is None:
        pytest.skip("no C compiler here: the compiled grid is not built (the PyTorch path trains)")
    return found


def _grids() -> list[VectorMatrixGrid]:
    torch.manual_seed(0)
    return [VectorMatrixGrid(8, (9, 7, 5)), VectorMatrixGrid(24, (6, 11, 13))]


def _points(count: int = 4000) -> torch.Tensor:
    return torch.rand(count, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1


@pytest.fixture()
def one_thread_read(monkeypatch):
    grids, x = _grids(), _points()
    with monkeypatch.context() as one_thread, torch.no_grad():
        one_thread.setattr(torch, "get_num_threads", lambda: 1)
        expected = compiled_grid.read_grids(grids, x)
    return grids, x, expected


def test_thread_counts_changing_from_call_to_call_give_the_one_threads_result(one_thread_read, monkeypatch):
    grids, x, expected = one_thread_read
    counts = [2, 4, 1, 3, 2, 2, 5, 1, 2] * 20
    for call, threads in enumerate(counts):
        monkeypatch.setattr(torch, "get_num_threads", lambda threads=threads: threads)
        if call % 17 == 0:
            time.sleep(0.005)  # past the workers' 0.5 ms spin: they sleep and must be woken
        with torch.no_grad():
            assert torch.equal(compiled_grid.read_grids(grids, x), expected), f"call {call}, {threads} threads"


def test_many_workers_on_two_cores_with_jobs_of_few_items_between_give_the_one_threads_result(monkeypatch):
    """Jobs of up to 8 items on this machine's 2 cores, jobs of 2 between: the workers without
    an item in a job are neither woken nor waited for, so on oversubscribed cores they fall
    behind and then read a job they missed (its slot, then the generation again). The window
    where a late worker could take the next job's fields is narrow: these calls run that path,
    they cannot force the race (with one slot and no second read they passed three runs)."""
    grids, x = _grids(), _points(8192)
    with monkeypatch.context() as one_thread, torch.no_grad():
        one_thread.setattr(torch, "get_num_threads", lambda: 1)
        expected = compiled_grid.read_grids(grids, x)
    for call, threads in enumerate([8, 2, 6, 1, 2, 3, 8, 2, 2, 7] * 60):
        monkeypatch.setattr(torch, "get_num_threads", lambda threads=threads: threads)
        with torch.no_grad():
            assert torch.equal(compiled_grid.read_grids(grids, x), expected), f"call {call}, {threads} threads"


def test_two_callers_at_once_both_get_the_one_threads_result(one_thread_read, monkeypatch):
    grids, x, expected = one_thread_read
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    wrong: list[int] = []

    def call_many() -> None:
        for call in range(150):
            with torch.no_grad():
                if not torch.equal(compiled_grid.read_grids(grids, x), expected):
                    wrong.append(call)

    callers = [threading.Thread(target=call_many) for _ in range(2)]
    for caller in callers:
        caller.start()
    for caller in callers:
        caller.join(timeout=120)
    assert not any(caller.is_alive() for caller in callers), "a caller hung"
    assert wrong == []


def _read_in_child(connection) -> None:
    grids, x = _grids(), _points()
    with torch.no_grad():
        connection.send(compiled_grid.read_grids(grids, x).numpy())


def test_a_forked_child_starts_its_own_workers(one_thread_read, monkeypatch):
    grids, x, expected = one_thread_read
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    with torch.no_grad():
        compiled_grid.read_grids(grids, x)  # the parent's workers exist before the fork
    context = multiprocessing.get_context("fork")
    receiving, sending = context.Pipe(duplex=False)
    child = context.Process(target=_read_in_child, args=(sending,))
    child.start()
    assert receiving.poll(120), "the forked child's two-thread read hung"
    assert torch.equal(torch.from_numpy(receiving.recv()), expected)
    child.join(timeout=60)
    assert child.exitcode == 0
