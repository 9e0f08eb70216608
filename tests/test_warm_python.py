"""The tests' warm interpreter (tests/warm_python.py) runs a module as a cold ``python -m`` would:
the same output, exit status, folder, arguments and environment, its own process with torch's
threads working, Python's normal exit, a timeout that kills, and no module of this project
imported before the command imports it."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from conftest import REPO_ROOT, WARM, run_python
from warm_python import WarmInterpreter

PROBE = r'''
import atexit, json, os, sys, threading, time
import torch

def leave_a_mark():
    with open("atexit.txt", "w") as f:
        f.write("ran")

def late_thread():
    time.sleep(0.3)
    with open("thread.txt", "w") as f:
        f.write("joined")

atexit.register(leave_a_mark)
threading.Thread(target=late_thread).start()
# A parallel reduction over both threads: a fork that copied a started OpenMP pool would hang here.
torch.set_num_threads(2)
total = torch.ones(4_000_000).sum().item()
print(json.dumps({
    "cwd": os.getcwd(), "argv": sys.argv[1:], "marker": os.environ.get("NERF_PROBE_MARKER"),
    "pid": os.getpid(), "project_modules": sorted(m for m in sys.modules if m.split(".")[0] in
        ("nerf_backend", "datasets_gen", "nerf_contract", "conftest", "warm_python")),
    "threads": torch.get_num_threads(), "total": total, "main": __name__,
    "path0": sys.path[0],
}))
print("to stderr\r\nand a bar\rredrawn", file=sys.stderr)
sys.exit(int(sys.argv[1]))
'''


@pytest.fixture
def probe_folder(tmp_path):
    (tmp_path / "probe.py").write_text(PROBE)
    return tmp_path


@pytest.fixture
def warm():
    interpreter = WarmInterpreter(REPO_ROOT, modules=("probe",))
    yield interpreter
    interpreter.stop()


def test_a_warm_command_is_the_cold_one(warm, probe_folder):
    env = {**os.environ, "NERF_PROBE_MARKER": "set by the test"}
    args = ("-m", "probe", "3", "an argument with spaces")
    assert warm.can_run(args, env)
    warm_result = warm.run(args, probe_folder, env, timeout=120)
    cold_result = subprocess.run([sys.executable, *args], cwd=probe_folder, env=env, capture_output=True, text=True,
                                 timeout=120)
    warm_facts, cold_facts = json.loads(warm_result.stdout), json.loads(cold_result.stdout)
    assert warm_result.returncode == cold_result.returncode == 3
    assert warm_result.stderr == cold_result.stderr == "to stderr\nand a bar\nredrawn\n"
    assert warm_facts.pop("pid") not in (os.getpid(), warm.process.pid)
    cold_facts.pop("pid")
    assert warm_facts == cold_facts
    assert warm_facts["project_modules"] == [] and warm_facts["threads"] == 2 and warm_facts["total"] == 4_000_000
    assert warm_facts["cwd"] == str(probe_folder) and warm_facts["marker"] == "set by the test"
    # Python's normal exit: a non-daemon thread joined and the atexit handlers run.
    assert (probe_folder / "thread.txt").read_text() == "joined" and (probe_folder / "atexit.txt").read_text() == "ran"
    # The server lives on for the next command, and an uncaught exception exits 1 with its traceback.
    (probe_folder / "raising.py").write_text("raise ValueError('from the probe')\n")
    warm.modules = ("raising",)
    raised = warm.run(("-m", "raising"), probe_folder, env, timeout=120)
    assert raised.returncode == 1 and raised.stderr.rstrip().endswith("ValueError: from the probe")


def test_a_command_past_its_timeout_is_killed(warm, tmp_path):
    (tmp_path / "sleeper.py").write_text("import time\nprint('started', flush=True)\ntime.sleep(600)\n")
    warm.modules = ("sleeper",)
    with pytest.raises(subprocess.TimeoutExpired) as expired:
        warm.run(("-m", "sleeper"), tmp_path, dict(os.environ), timeout=3)
    assert expired.value.output == b"started\n"
    assert warm.process.poll() is None, "the server survives a killed command"


def test_what_runs_cold(warm):
    env = dict(os.environ)
    assert not warm.can_run(("-c", "print(1)"), env) and not warm.can_run(("-m", "datasets_gen"), env)
    # A variable read when the interpreter or a library starts cannot change in a fork.
    assert not warm.can_run(("-m", "probe"), {**env, "OMP_NUM_THREADS": "7"})
    assert not warm.can_run(("-m", "probe"), {**env, "PYTHONHASHSEED": "1"})
    assert not warm.can_run(("-m", "probe"), {**env, "LD_PRELOAD": "/lib/x.so"})
    assert warm.can_run(("-m", "probe"), {**env, "NERF_ANYTHING": "1", "TORCH_HOME": "/elsewhere",
                                          "MATERIALX_SEARCH_PATH": "/set/by/bpy"})


def test_run_python_forks_backend_commands_warm():
    """conftest's run_python: the backend's own error path, warm, as a user sees it cold."""
    args = ("-m", "nerf_backend", "eval", "/nonexistent/run")
    assert WARM.can_run(args, os.environ)
    warm_result = run_python(*args, check=False)
    cold_result = subprocess.run([sys.executable, *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert (warm_result.returncode, warm_result.stdout, warm_result.stderr) == \
        (cold_result.returncode, cold_result.stdout, cold_result.stderr)
    assert warm_result.returncode == 2 and "/nonexistent/run" in warm_result.stderr
