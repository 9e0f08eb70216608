"""The Flamenco job type (tools/flamenco/nerf_dataset.js), compiled by Node against a stand-in
for Flamenco's job-compiler API (tests/flamenco_standin.js), and its tasks' commands run here
with a real Blender binary: the shards and the merge must give the dataset one run gives."""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import pytest

from conftest import REPO_ROOT, SHARED_DIR
from test_datasets_gen import require_blender
from test_datasets_gen_runs import assert_same_dataset

JOB_TYPE = REPO_ROOT / "tools" / "flamenco" / "nerf_dataset.js"
STANDIN = REPO_ROOT / "tests" / "flamenco_standin.js"
# Flamenco's variables as a Linux worker with Debian's Blender would have them.
VARIABLES = {"{blender}": None, "{blenderArgs}": "-b -y"}
TINY = "--resolution 16 --train-views 6 --val-views 2 --test-views 3 --samples 4 --seed 1"


def node() -> str:
    found = shutil.which("node") or shutil.which("nodejs")
    if found is None:
        if os.environ.get("NERF_REQUIRE_NODE"):
            pytest.fail("Node is required here (NERF_REQUIRE_NODE) but not installed")
        pytest.skip("no Node on this machine (Debian: apt-get install nodejs)")
    return found


def compile_job(settings: dict) -> subprocess.CompletedProcess:
    return subprocess.run([node(), str(STANDIN), str(JOB_TYPE), json.dumps(settings)], capture_output=True, text=True,
                          timeout=60)


def command_line(command: dict, blender: str) -> list[str]:
    """The argv a Flamenco worker runs for a command: blender-render is exe, exeArgs,
    argsBefore, the blend file and args; exec is exe and args."""
    parameters = command["parameters"]

    def expand(text: str) -> list[str]:
        for name, value in {**VARIABLES, "{blender}": blender}.items():
            text = text.replace(name, value)
        return text.split()

    if command["type"] == "blender-render":
        return [*expand(parameters["exe"]), *expand(parameters["exeArgs"]), *parameters["argsBefore"],
                parameters["blendfile"], *parameters["args"]]
    assert command["type"] == "exec", command
    return [*expand(parameters["exe"]), *parameters["args"]]


def test_the_job_compiles_into_shards_and_a_merge_that_depends_on_them(tmp_path):
    result = compile_job({"datasets_gen_root": "/farm/nerf/", "out_dir": "/farm/out/ds", "shards": 3,
                          "generator_args": "--resolution 800  --samples 128", "blendfile": "/farm/scene.blend"})
    assert result.returncode == 0, result.stderr
    job = json.loads(result.stdout)
    assert job["label"] == "NeRF Dataset (datasets_gen)"
    *renders, merge = job["tasks"]
    assert [task["name"] for task in renders] == [f"datasets_gen shard {k} of 3" for k in (1, 2, 3)]
    for index, task in enumerate(renders):
        (command,) = task["commands"]
        assert command["type"] == "blender-render" and command["parameters"]["blendfile"] == "/farm/scene.blend"
        assert command["parameters"]["args"] == [
            "--python", "/farm/nerf/datasets_gen/generate.py", "--", "--resolution", "800", "--samples", "128",
            "--out", "/farm/out/ds", "--shard", f"{index}/3", "--no-progress"]
        assert task["dependencies"] == []
    assert merge["dependencies"] == [task["name"] for task in renders]
    assert merge["commands"][0]["parameters"]["args"][-2:] == ["--merge", "/farm/out/ds"]
    # Defaults are Flamenco's to fill; bad settings stop the compile with a message.
    default = compile_job({"datasets_gen_root": "/r", "out_dir": "/o", "blendfile": "/b.blend"})
    assert len(json.loads(default.stdout)["tasks"]) == 5  # 4 shards and the merge
    for bad, message in (({"shards": 0}, "shards must be a whole number"),
                         ({"generator_args": "--out /elsewhere"}, "--out is set by the job itself")):
        refused = compile_job({"datasets_gen_root": "/r", "out_dir": "/o", "blendfile": "/b.blend", **bad})
        assert refused.returncode == 2 and message in refused.stderr, refused.stderr


def test_the_compiled_commands_reproduce_a_single_run(tmp_path):
    blender = require_blender()
    scene = SHARED_DIR / "scenes" / "A.blend"
    out = tmp_path / "farm"
    result = compile_job({"datasets_gen_root": str(REPO_ROOT), "out_dir": str(out), "shards": 2,
                          "generator_args": TINY, "blendfile": str(scene)})
    assert result.returncode == 0, result.stderr
    tasks = json.loads(result.stdout)["tasks"]
    done: set[str] = set()
    for task in tasks:  # in an order the dependencies allow, as the Manager would hand them out
        assert set(task["dependencies"]) <= done, task
        for command in task["commands"]:
            run = subprocess.run(command_line(command, blender), capture_output=True, text=True, timeout=300)
            assert run.returncode == 0, run.stderr[-2000:]
        done.add(task["name"])
    reference = tmp_path / "one"
    single = subprocess.run([blender, "-b", "-y", str(scene), "--python", str(REPO_ROOT / "datasets_gen" / "generate.py"),
                             "--", *TINY.split(), "--out", str(reference), "--no-progress"],
                            capture_output=True, text=True, timeout=300)
    assert single.returncode == 0, single.stderr[-2000:]
    assert_same_dataset(out, reference)
