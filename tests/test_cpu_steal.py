"""The hypervisor's share of the cores (``core/cpu_steal.py``) from /proc/stat's counters, and
its place beside the timings that it may slow (renders.json, bench-step's page)."""

from __future__ import annotations

from pathlib import Path

import pytest

from nerf_backend.core.cpu_steal import StealMeter, cpu_counters, steal_note, stolen_share

# user nice system idle iowait irq softirq steal guest guest_nice
STAT = "cpu  {user} 5 300 {idle} 10 0 20 {steal} 40 0\ncpu0 1 2 3 4 5 6 7 8 9 10\n"


def _write(path: Path, user: int, idle: int, steal: int) -> None:
    path.write_text(STAT.format(user=user, idle=idle, steal=steal))


def test_the_counters_are_the_steal_column_and_the_sum_of_the_first_eight(tmp_path):
    stat = tmp_path / "stat"
    _write(stat, user=1000, idle=2000, steal=50)
    # guest (40) is inside user already: not counted twice
    assert cpu_counters(stat) == (50, 1000 + 5 + 300 + 2000 + 10 + 0 + 20 + 50)


def test_the_share_between_two_readings(tmp_path):
    stat = tmp_path / "stat"
    _write(stat, user=1000, idle=2000, steal=50)
    with StealMeter(stat) as meter:
        _write(stat, user=1600, idle=2300, steal=150)  # 1 000 jiffies later, 100 of them stolen
    assert meter.share == pytest.approx(0.1)
    assert "10.0 %" in steal_note(meter.share)


@pytest.mark.parametrize("text", ["", "intr 1 2 3\n", "cpu 1 2 3\n", "cpu a b c d e f g h\n"])
def test_no_counters_where_the_file_holds_none(tmp_path, text):
    stat = tmp_path / "stat"
    stat.write_text(text)
    assert cpu_counters(stat) is None
    assert cpu_counters(tmp_path / "absent") is None
    with StealMeter(stat) as meter:
        pass
    assert meter.share is None and steal_note(meter.share) == ""


def test_no_share_where_no_time_passed():
    assert stolen_share((5, 100), (5, 100)) is None
    assert stolen_share(None, (5, 100)) is None
