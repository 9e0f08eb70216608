"""How much of the machine's CPU time a hypervisor gave to other guests while something was
timed (Linux's "steal" time, ``/proc/stat``), so a speed figure taken on a shared virtual
machine says so. On the 2-core VMs this project is measured on, the same `eval` took 12.6 s
with 0.7 % of the cores' time stolen and 16.1 s with 11.3 % (docs/benchmarks_lego.md,
session 69).

Example:
    >>> before, after = (100, 1000), (130, 1100)  # (stolen, all) jiffies
    >>> stolen_share(before, after)
    0.3
"""

from __future__ import annotations

from pathlib import Path

PROC_STAT = Path("/proc/stat")


def cpu_counters(path: Path = PROC_STAT) -> tuple[int, int] | None:
    """The machine's stolen and total CPU time so far, in jiffies (``/proc/stat``'s ``cpu``
    line: user nice system idle iowait irq softirq steal ...); None where the file is absent
    (not Linux) or has no steal column."""
    try:
        first = path.read_text().splitlines()[0].split()
    except (OSError, IndexError):
        return None
    if len(first) < 9 or first[0] != "cpu":
        return None
    try:
        values = [int(v) for v in first[1:9]]  # guest time is counted in user already
    except ValueError:
        return None
    return values[7], sum(values)


def stolen_share(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float | None:
    """The share of the CPU time between two ``cpu_counters`` readings that the hypervisor took;
    None where either reading is missing or no time passed."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return (after[0] - before[0]) / (after[1] - before[1])


class StealMeter:
    """``with StealMeter() as meter: ...``, then ``meter.share``: the stolen share of that
    block's CPU time (None off Linux)."""

    def __init__(self, path: Path = PROC_STAT) -> None:
        self.path, self.share, self._start = path, None, None

    def __enter__(self) -> "StealMeter":
        self._start = cpu_counters(self.path)
        return self

    def __exit__(self, *exc: object) -> None:
        self.share = stolen_share(self._start, cpu_counters(self.path))


def steal_note(share: float | None, threshold: float = 0.02) -> str:
    """A sentence for a page of timings when the hypervisor took at least ``threshold`` of the
    cores' time; '' otherwise.

    Example:
        >>> steal_note(0.113)
        "The hypervisor took 11.3 % of the cores' time while this was timed (Linux's steal time): the figures read slower than the machine is."
        >>> steal_note(0.004)
        ''
    """
    if share is None or share < threshold:
        return ""
    return (f"The hypervisor took {100 * share:.1f} % of the cores' time while this was timed (Linux's steal "
            "time): the figures read slower than the machine is.")
