"""A short ``bench`` run writes every output with sane values."""

from __future__ import annotations

import json

from PIL import Image

from conftest import run_python
from nerf_backend.bench import time_to_reach


def test_short_bench_writes_json_table_and_plot(tiny_demo_dataset, tmp_path):
    out = tmp_path / "bench"
    result = run_python("-m", "nerf_backend", "bench", str(tiny_demo_dataset), "--presets",
                        "fast,auto,slim=preview+field.width=32", "--iters", "6", "--points", "2",
                        "--curve-views", "2", "--out", str(out))
    report = json.loads((out / "bench.json").read_text())
    assert [v["name"] for v in report["variants"]] == ["fast", "auto", "slim"]
    for variant in report["variants"]:
        curve = variant["curve"]
        assert [p["iteration"] for p in curve] == sorted(p["iteration"] for p in curve)
        assert curve[-1]["iteration"] == variant["final"]["iterations"] == 6
        assert all(0 < p["train_seconds"] and 5 < p["psnr"] < 60 and 0 < p["ssim"] <= 1 for p in curve)
        assert variant["final"]["test_views"] == 4
        assert set(variant["time_to_psnr_s"]) == {"20", "25", "30"}
        assert 0 < variant["render_seconds_per_image"] < 60
        assert 50 < variant["peak_memory_mb"] < 20_000
        assert 0 < variant["model_size_mb"] < 100
    slim = report["variants"][2]
    assert slim["preset"] == "preview" and slim["overrides"] == ["field.width=32"]
    table = (out / "bench.md").read_text()
    assert table.count("\n| ") == 1 + 1 + 3  # header, rule, one row a variant
    with Image.open(out / "bench.png") as plot:
        assert plot.size[0] > 400 and plot.size[1] > 300
    assert "bench.json" in result.stdout


def test_time_to_reach_interpolates_between_points():
    curve = [{"train_seconds": 10.0, "psnr": 18.0}, {"train_seconds": 20.0, "psnr": 22.0},
             {"train_seconds": 40.0, "psnr": 31.0}]
    assert time_to_reach(curve, 20.0) == 15.0
    assert time_to_reach(curve, 30.0) == 20.0 + 20.0 * 8 / 9
    assert time_to_reach(curve, 32.0) is None
