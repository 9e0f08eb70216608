"""What a new user meets on a first run: progress on a terminal and in a log file, a finished
run resumed with nothing to do, the files a run leaves behind and their modes."""

from __future__ import annotations

import argparse
import fcntl
import io
import json
import os
import pty
import select
import stat
import struct
import subprocess
import sys
import termios

import pytest

from conftest import REPO_ROOT, run_python
from nerf_backend.core import progress as progress_module
from nerf_backend.core.progress import Progress

BUDGET_S = "4"


def _train_on_a_terminal(*args: str) -> tuple[int, str]:
    """``python -m nerf_backend train ARGS`` with stderr on a pseudo-terminal (so the bar is
    drawn): the exit status and everything written to the terminal."""
    master, slave = pty.openpty()
    # A terminal 120 columns wide (a fresh pseudo-terminal has no size, and tqdm then draws nothing).
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    process = subprocess.Popen([sys.executable, "-m", "nerf_backend", "train", *args], cwd=REPO_ROOT,
                               stdin=subprocess.DEVNULL, stdout=slave, stderr=slave)
    os.close(slave)
    chunks = []
    while True:
        ready, _, _ = select.select([master], [], [], 600)
        if not ready:
            process.kill()
            raise AssertionError("train wrote nothing to its terminal for 600 s")
        try:
            chunk = os.read(master, 65536)
        except OSError:  # the child closed the terminal (Linux: EIO)
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(master)
    return process.wait(timeout=60), b"".join(chunks).decode(errors="replace")


@pytest.mark.parametrize("stop", [("--max-seconds", BUDGET_S), ("--iters", "40")], ids=["budget", "iterations"])
def test_a_finished_run_resumed_on_a_terminal_has_nothing_to_do(tiny_demo_dataset, tmp_path, stop):
    """make demo's train stage twice, with the bar drawn (the demo stops at an iteration count;
    a time budget is the other way a run ends). With a budget, the second run's recorded time
    is already past it (the first run always overshoots by part of a step), and tqdm once
    failed on a bar whose start lay past its end. It must end cleanly, saying so."""
    run = tmp_path / "run"
    status, first = _train_on_a_terminal(str(tiny_demo_dataset), "--preset", "fast", "--out", str(run), *stop)
    assert status == 0, first
    assert "\r" in first and "train fast" in first  # a bar was drawn, redrawn in place
    status, second = _train_on_a_terminal(str(tiny_demo_dataset), "--out", str(run), *stop, "--resume")
    assert status == 0, second
    assert "Traceback" not in second and "error" not in second.lower(), second
    assert "nothing to do" in second.lower(), second


def test_a_log_file_gets_lines_not_a_redrawn_bar(tiny_demo_dataset, tmp_path):
    """stderr to a file (a log that people keep): no carriage returns, a few lines, small."""
    run = tmp_path / "run"
    log = tmp_path / "run.log"
    with open(log, "w") as handle:
        subprocess.run([sys.executable, "-m", "nerf_backend", "train", str(tiny_demo_dataset), "--preset", "fast",
                        "--out", str(run), "--max-seconds", "4"], cwd=REPO_ROOT, stdout=handle, stderr=handle,
                       check=True, timeout=600)
    text = log.read_text()
    assert "\r" not in text, text[:500]
    lines = text.splitlines()
    # A line every 10 s of wall time (spaced as test_plain_progress_lines_are_spaced_and_clamped
    # checks) and one at the end, plus the summary; 4 s of training are enough for tqdm's bar,
    # which redraws itself with "\r" within its first tenth of a second.
    assert 1 <= len(lines) <= 12 and log.stat().st_size < 2000, text


def test_plain_progress_lines_are_spaced_and_clamped(monkeypatch):
    """Off a terminal: the first line waits for the interval, the last comes at close; a start
    past the total (a resumed run past its budget) is clamped, not an error."""
    stream = io.StringIO()
    bar = Progress(120, "train", initial=121.5, seconds=True, stream=stream)
    assert not bar.terminal and bar.n == 120
    bar.update(5)
    assert stream.getvalue() == ""  # the interval has not passed
    monkeypatch.setattr(progress_module, "LINE_INTERVAL_S", 0.0)
    bar.set_postfix(it=7)
    bar.advance_to(200)
    bar.close()
    assert stream.getvalue().splitlines() == ["train: 120/120 s (0 s elapsed, it=7)"] * 2
    quiet = io.StringIO()
    silent = Progress(10, "render", enabled=False, stream=quiet)
    silent.update(10)
    silent.write("a message the user must see")
    silent.close()
    assert quiet.getvalue() == "a message the user must see\n"


def test_a_finished_run_leaves_no_lock_and_files_follow_the_umask(trained_run):
    """The lock file goes with the trainer; files written through temporaries get the mode any
    new file gets (a shared report must not show unreadable images)."""
    assert not (trained_run / ".lock").exists()
    mask = os.umask(0o022)
    os.umask(mask)
    expected = 0o666 & ~mask
    for name in ("checkpoint.pt", "config.json", "preview.png", "events.jsonl"):
        assert stat.S_IMODE((trained_run / name).stat().st_mode) == expected, name


def test_the_usage_lines_name_the_projects_python(tmp_path):
    """With a Python that lacks torch (here: one told to ignore the venv's packages), one line
    saying which Python to use, not a traceback."""
    result = subprocess.run([sys.executable, "-S", "-m", "nerf_backend", "--help"], cwd=REPO_ROOT,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode != 0
    assert "Traceback" not in result.stderr and ".venv/bin/python" in result.stderr, result.stderr
    help_text = run_python("-m", "nerf_backend", "--help").stdout
    assert "``" not in help_text


def test_train_without_a_preset_trains_auto(tiny_demo_dataset, tmp_path):
    """A new user's `train DATASET --out RUN` gets the preset the README and the add-on use."""
    run = tmp_path / "run"
    run_python("-m", "nerf_backend", "train", str(tiny_demo_dataset), "--out", str(run), "--iters", "3",
               "--no-progress")
    assert json.loads((run / "config.json").read_text())["preset"] == "auto"


def test_every_commands_help_shows_its_defaults():
    from nerf_backend.cli import build_parser

    parser = build_parser()
    commands = next(action for action in parser._actions if isinstance(action, argparse._SubParsersAction)).choices
    missing = []
    for name, command in commands.items():
        formatter = command._get_formatter()
        for action in command._actions:
            if not action.option_strings or action.default in (None, False, [], argparse.SUPPRESS):
                continue
            if "default" not in formatter._get_help_string(action):
                missing.append(f"{name} {action.option_strings[0]}")
    assert not missing, missing
    assert "(default: auto)" in commands["train"].format_help().replace("\n", " ").replace("  ", " ")
