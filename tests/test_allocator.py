"""core/allocator.py: with glibc's allocator kept from handing large freed blocks back to the
kernel, rendering a view again reuses the last view's pages; without it, each chunk's buffers
are faulted in afresh. Each case in a process of its own (the setting is the process's): a
512×512 view of a model of random smooth density (4 chunks of rays), rendered 3 times after two
untimed views, transparent huge pages off for the process (so that a fault is a 4 KB page on any
kernel's setting). Measured: 540-1 070 faults a view kept, 35 100-36 300 with the threshold pinned
(below).

The case without the setting pins glibc's mmap threshold at its starting 128 KiB. Left to
itself, glibc raises the threshold to the size of each mmapped block freed, so whether the next
view's buffers come from fresh pages depends on the order of the process's earlier frees: a
clean clone once counted 6 428 faults a view there where 10 800-14 100 is usual.
Pinned, every large block is the kernel's afresh, which is what the setting is measured against."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from nerf_backend.core.allocator import USER_VARIABLES, keep_freed_memory

PROGRAM = """
import ctypes, json, resource, sys
ctypes.CDLL(None).prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: faults counted in 4 KB pages wherever THP is on
from nerf_backend.core.allocator import keep_freed_memory
kept = keep_freed_memory() if sys.argv[1] == "keep" else False
if sys.argv[1] == "fresh":  # glibc's starting threshold, pinned (mallopt turns its moving off)
    assert ctypes.CDLL(None).mallopt(-3, 128 * 1024) == 1  # M_MMAP_THRESHOLD
import torch
from nerf_backend.configs.presets import PRESETS
from nerf_backend.core.cameras import Intrinsics
from nerf_backend.core.scene_bounds import SceneBounds
from nerf_backend.evaluation.render_views import render_image
from nerf_backend.model_components.ray_bounds import RayBounds
from nerf_backend.models.registry import build_model
torch.manual_seed(0)
box = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
model = build_model(PRESETS["auto"], box)
with torch.no_grad():
    for parameter in model.field.encoding_parameters():
        parameter.normal_(0.0, 1.4)
model.update_occupancy()
model.eval()
pose = torch.eye(4)
pose[2, 3] = 4.0
view = (model, Intrinsics(512, 512, 600.0, 600.0, 256.0, 256.0), pose, RayBounds(box=box))
# Two untimed views: the first also builds the density volume (its transposed planes freed at
# once); the timed views then reuse (or fault in) only a view's own buffers.
render_image(*view)
render_image(*view)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(3):
    image = render_image(*view)
faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 3
print(json.dumps({"kept": kept, "faults": faults, "opacity": float(image.opacity.mean())}))
"""


def _render(mode: str) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    for name in USER_VARIABLES:
        env.pop(name, None)
    done = subprocess.run([sys.executable, "-c", PROGRAM, mode], capture_output=True, text=True, env=env,
                          check=True, timeout=300)
    return json.loads(done.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_a_view_rendered_again_reuses_the_pages_of_the_last():
    kept, fresh = _render("keep"), _render("fresh")
    assert kept["kept"] and not fresh["kept"]
    assert 0.1 < kept["opacity"] == fresh["opacity"] < 0.9  # the same image, of something
    assert fresh["faults"] > 20000  # each chunk's buffers faulted in again
    assert kept["faults"] < fresh["faults"] / 4


def test_the_users_own_setting_is_left_alone(monkeypatch):
    monkeypatch.setenv(USER_VARIABLES[1], "1000000")
    assert keep_freed_memory() is False
