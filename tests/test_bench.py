"""A short ``bench`` run writes every output with sane values."""

from __future__ import annotations

import ctypes
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from PIL import Image

from conftest import REPO_ROOT, run_python
from nerf_backend.bench import Variant, ablation_order, ablation_variants, time_to_reach
from nerf_backend.configs.presets import PRESETS
from nerf_backend.data.run_folder import LOCK_NAME, RunFolder
from nerf_backend.fields.mlp_field import NerfField
from nerf_backend.kernels.build import load_kernel
from nerf_backend.bench.plain_nerf import PlainMLP, fourier_features


def test_short_bench_writes_json_table_and_plot(tiny_demo_dataset, tmp_path):
    out = tmp_path / "bench"
    page = tmp_path / "pages" / "bench_demo_40px.md"
    result = run_python("-m", "nerf_backend", "bench", str(tiny_demo_dataset), "--presets",
                        "fast,auto,slim=preview+field.width=32", "--iters", "6", "--points", "2,6",
                        "--curve-views", "2", "--out", str(out), "--page", str(page))
    report = json.loads((out / "bench.json").read_text())
    assert [v["name"] for v in report["variants"]] == ["fast", "auto", "slim"]
    for variant in report["variants"]:
        curve = variant["curve"]
        assert [p["iteration"] for p in curve] == [2, 6]  # the points asked for
        assert variant["final"]["iterations"] == 6
        assert all(0 < p["train_seconds"] and 5 < p["psnr"] < 60 and 0 < p["ssim"] <= 1 for p in curve)
        assert variant["final"]["test_views"] == 4
        assert set(variant["time_to_psnr_s"]) == {"20", "25", "30"}
        assert 0 < variant["render_seconds_per_image"] < 60
        assert 50 < variant["peak_memory_mb"] < 20_000
        assert 0 < variant["model_size_mb"] < 100
    for variant in report["variants"]:  # throughput over the whole run, its resumed segments included
        final = variant["final"]
        rays_per_batch = json.loads((out / "runs" / variant["name"] / "config.json").read_text())["config"][
            "rays_per_batch"]
        assert final["rays_per_second"] * final["train_seconds"] == pytest.approx(6 * rays_per_batch, rel=1e-9)
        assert final["samples_per_second"] > 0
    slim = report["variants"][2]
    assert slim["preset"] == "preview" and slim["overrides"] == ["field.width=32"]
    # The tiny demo has a true surface: each variant's final mesh is measured against it (a
    # variant 6 iterations in may have no surface at the threshold yet: then None and why).
    assert report["geometry"]["mesh_resolution"] == 128 and report["geometry"]["tau"] > 0
    for variant in report["variants"]:
        final = variant["final"]
        assert final["chamfer"] is None and final["geometry_unavailable"] or 0 < final["chamfer"] < 1
    table = (out / "bench.md").read_text()
    assert table.count("\n| ") == 1 + 1 + 3  # header, rule, one row a variant
    # The command as typed and the commit that made the figures, in the JSON and the table.
    command = (f"python -m nerf_backend bench {tiny_demo_dataset} --presets fast,auto,slim=preview+field.width=32 "
               f"--iters 6 --points 2,6 --curve-views 2 --out {out} --page {page}")
    assert report["provenance"]["command"] == command
    commit = report["provenance"]["commit"]
    assert commit is None or re.fullmatch(r"[0-9a-f]{7,}(\+changes)?", commit), commit
    assert f"Made by `{command}` at commit " in table
    assert "| Chamfer | F-score at τ |" in table
    # What computed the figures: a GPU's name, or here the CPU and its vector extensions.
    assert report["machine"]["processor"] == f"CPU ({torch.backends.cpu.get_cpu_capability()})"
    assert f"on {report['machine']['threads']} threads, {report['machine']['processor']}." in table
    with Image.open(out / "bench.png") as plot:
        assert plot.size[0] > 400 and plot.size[1] > 300
    assert "bench.json" in result.stdout
    # --page: the table as a docs page, its plot beside it, and the folder's index listing it.
    assert page.read_text() == table.rstrip("\n") + "\n\n![bench_demo_40px](bench_demo_40px.png)\n"
    assert (page.with_suffix(".png")).read_bytes() == (out / "bench.png").read_bytes()
    index = (page.parent / "README.md").read_text()
    assert "| [bench_demo_40px](bench_demo_40px.md) | " in index and f"`{command}`" in index


def _without_true_surface(dataset: Path, folder: Path) -> Path:
    """A copy of ``dataset`` as a datasets_gen from before scene_geometry.ply wrote it: its
    profile names no true surface."""
    copy = folder / dataset.name
    shutil.copytree(dataset, copy)
    profile = json.loads((copy / "scene_profile.json").read_text())
    (copy / profile.pop("geometry")["file"]).unlink()
    (copy / "scene_profile.json").write_text(json.dumps(profile))
    return copy


def test_bench_at_several_budgets_trains_each_from_scratch_and_writes_the_trade(tiny_demo_dataset, tmp_path):
    """--budget-seconds 2,4: each budget its own bench from scratch (OUT/2s, OUT/4s), the trade
    across them in trade.{json,md,png}; the same command again keeps what is finished. On a
    dataset with no true surface: the benches score no geometry (the test above scores it), and
    the trade needs none."""
    dataset = _without_true_surface(tiny_demo_dataset, tmp_path)
    out = tmp_path / "trade"
    command = ["-m", "nerf_backend", "bench", str(dataset), "--presets", "fast,auto",
               "--budget-seconds", "4,2", "--points", "1", "--curve-views", "2", "--out", str(out)]
    result = run_python(*command)
    scene = dataset.name
    for budget in (2, 4):
        bench = json.loads((out / f"{budget}s" / scene / "bench.json").read_text())
        assert bench["budget"] == {"seconds": budget} and bench["geometry"] is None
        assert "Chamfer" not in (out / f"{budget}s" / scene / "bench.md").read_text()
        for variant in bench["variants"]:  # trained from scratch to this budget, not a point on a longer run
            assert budget <= variant["final"]["train_seconds"] < 2 * budget
            assert len(variant["curve"]) == 1 and "chamfer" not in variant["final"]
    trade = json.loads((out / "trade.json").read_text())
    assert trade["budgets_seconds"] == [2.0, 4.0]
    [summary] = trade["scenes"]
    assert summary["scene"] == scene and [v["variant"] for v in summary["variants"]] == ["fast", "auto"]
    for variant in summary["variants"]:
        for budget in ("2", "4"):
            cell = variant["by_budget"][budget]
            assert 5 < cell["psnr"] < 60 and cell["rays_per_second"] > 0 and cell["samples_per_second"] > 0
    for row in summary["budgets"]:
        cells = {v["variant"]: v["by_budget"][f"{row['budget_seconds']:g}"]["psnr"] for v in summary["variants"]}
        assert row["best_fixed"]["variant"] == "fast"
        assert row["auto"]["gap_to_best_fixed_db"] == pytest.approx(cells["auto"] - cells["fast"])
    table = (out / "trade.md").read_text()
    assert "| scene | variant | 2 s | 4 s |" in table and table.count(f"| {scene} | ") == 2 + 2
    with Image.open(out / "trade.png") as plot:
        assert plot.size[0] > 400
    assert "trade.json" in result.stdout
    again = run_python(*command)
    assert again.stderr.count("finished bench kept") == 2
    assert json.loads((out / "trade.json").read_text())["scenes"] == trade["scenes"]


def test_curve_points_beyond_the_budget_are_refused_before_any_training(tiny_demo_dataset, tmp_path):
    out = tmp_path / "bench"
    result = run_python("-m", "nerf_backend", "bench", str(tiny_demo_dataset), "--presets", "fast",
                        "--budget-seconds", "60", "--points", "30,90", "--out", str(out), check=False)
    assert result.returncode == 2
    assert "bench --points: curve points 30, 90 must lie within the budget (60)" in result.stderr
    assert not (out / "runs").exists()


def test_time_to_reach_interpolates_between_points():
    curve = [{"train_seconds": 10.0, "psnr": 18.0}, {"train_seconds": 20.0, "psnr": 22.0},
             {"train_seconds": 40.0, "psnr": 31.0}]
    assert time_to_reach(curve, 20.0) == 15.0
    assert time_to_reach(curve, 30.0) == 20.0 + 20.0 * 8 / 9
    assert time_to_reach(curve, 32.0) is None


def test_ablation_variants_and_their_order_against_the_paper():
    specs = ablation_variants("preview")
    variants = [Variant.parse(spec) for spec in specs]
    assert variants[0] == Variant("preview_full", "preview", ())
    by_name = {v.name: v for v in variants}
    assert by_name["preview_no_pe"].overrides == ("field.position_frequencies=0", "field.direction_frequencies=0")
    assert by_name["preview_25_views"].overrides == ("max_train_views=25",)
    psnr = {"full": 30.0, "no_pe": 28.0, "no_view_dependence": 31.0, "50_views": 29.0, "25_views": 27.0}
    results = [{"name": f"preview_{k}", "final": {"psnr": v}} for k, v in psnr.items()]
    checks = {c["claim"]: c["holds"] for c in ablation_order(results)}
    assert checks == {
        "preview_full > preview_no_pe": True,
        "preview_full > preview_no_view_dependence": False,  # 30 < 31: reported, not hidden
        "preview_full > preview_50_views": True,
        "preview_50_views > preview_25_views": True,
    }


def test_plain_yardstick_computes_the_same_field_as_the_project():
    """bench-step compares costs of the same maths: with the same weights, the plain MLP and
    the project's field give the same density and colour."""
    config = PRESETS["paper"]
    torch.manual_seed(0)  # a fixed initialisation whose ReLU density is not zero everywhere
    ours, plain = NerfField(config.field), PlainMLP(config)
    assert sum(p.numel() for p in plain.parameters()) == sum(p.numel() for p in ours.parameters()) == 595_844
    pairs = list(zip(ours.trunk, plain.layers)) + [(ours.density_head, plain.sigma), (ours.feature, plain.feature),
                                                   (ours.colour_hidden, plain.view), (ours.colour_head, plain.rgb)]
    with torch.no_grad():
        for source, target in pairs:
            target.weight.copy_(source.weight)
            target.bias.copy_(source.bias)
    x, d = torch.rand(500, 3) * 3 - 1.5, torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    sigma, rgb = ours(x, d)
    plain_sigma, plain_rgb = plain(fourier_features(x, 10), fourier_features(d, 4))
    assert torch.allclose(plain_sigma, sigma, atol=1e-5) and torch.allclose(plain_rgb, rgb, atol=1e-5)
    assert sigma.max() > 0  # not a trivially dead field


def test_bench_step_times_both_sides(tiny_demo_dataset, tmp_path):
    out = tmp_path / "step"
    result = run_python("-m", "nerf_backend", "bench-step", str(tiny_demo_dataset), "--preset", "preview",
                        "--rays", "64", "--steps", "2", "--out", str(out))
    report = json.loads((out / "step_cost.json").read_text())
    seconds = report["seconds_per_iteration"]
    assert 0 < seconds["project"] < 30 and 0 < seconds["plain"] < 30
    assert report["ratio_project_to_plain"] == seconds["project"] / seconds["plain"]
    assert report["parameters"]["project"] == report["parameters"]["plain"]
    assert report["rays_per_batch"] == 64 and report["steps"] == 2
    assert "plain PyTorch" in result.stdout


def test_the_compiled_line_gather_reads_every_row_it_is_given():
    """kernels/machine_rates.c (bench-step's random-line rate) reads exactly the rows asked
    for, on one thread or several: the sum of their first values, to float rounding."""
    library = load_kernel("machine_rates")[0]
    if library is None:
        pytest.skip("no C compiler: the rate is PyTorch's gather alone")
    library.gather_lines.restype = ctypes.c_float
    rows = torch.arange(4096 * 16, dtype=torch.float32).view(4096, 16) / 16  # row r's first value is r
    index = torch.randint(4096, (50_000,), generator=torch.Generator().manual_seed(0))
    for threads in (1, 2, 3):
        total = library.gather_lines(ctypes.c_void_p(rows.data_ptr()), ctypes.c_void_p(index.data_ptr()),
                                     ctypes.c_int64(index.numel()), ctypes.c_int64(threads))
        assert total == pytest.approx(float(index.double().sum()), rel=1e-5)


def test_the_random_line_rate_is_the_faster_of_pytorch_and_the_compiled_loop(monkeypatch):
    """A reference must stay a lower bound: the compiled loop's time counts where it is shorter
    than PyTorch's, and PyTorch's alone where there is no compiler."""
    import nerf_backend.bench.hardware as hardware
    monkeypatch.setattr(hardware, "_compiled_lines_seconds", lambda rows, index, repeats: 1e-3)
    assert hardware.measure_hardware(torch.device("cpu"), repeats=1, table_bytes=2**22)["lines_m_s"] == (
        pytest.approx(2**20 / 1e-3 / 1e6))  # 2^20 lines in a millisecond: faster than any gather here
    monkeypatch.setattr(hardware, "_compiled_lines_seconds", lambda rows, index, repeats: None)
    assert 1 < hardware.measure_hardware(torch.device("cpu"), repeats=1, table_bytes=2**22)["lines_m_s"] < 2**20 / 1e-3 / 1e6


def test_bench_step_profiles_a_marched_preset_by_stage(tiny_demo_dataset, tmp_path):
    """A marched preset's step and rendered view split by stage, against measured rates."""
    out = tmp_path / "profile"
    page = tmp_path / "pages" / "step_profile_demo_40px.md"
    result = run_python("-m", "nerf_backend", "bench-step", str(tiny_demo_dataset), "--preset", "auto",
                        "--warmup-seconds", "4", "--out", str(out), "--page", str(page))
    report = json.loads((out / "step_profile.json").read_text())
    # Its page says the command and the commit the table itself does not.
    assert page.read_text().startswith((out / "step_profile.md").read_text().rstrip("\n"))
    assert f"Made by `python -m nerf_backend bench-step {tiny_demo_dataset} --preset auto" in page.read_text()
    assert "step_profile_demo_40px.md" in (page.parent / "README.md").read_text()
    hardware = report["hardware"]
    assert hardware["gflops"] > 1 and hardware["bandwidth_gb_s"] > 0.5 and hardware["lines_m_s"] > 1
    training = report["training"]
    stages = {row["stage"]: row for row in training["stages"]}
    assert list(stages) == ["data", "rays", "upkeep", "march", "density pass", "field", "composite", "loss",
                            "backward", "optimiser", "other"]
    assert 0 < training["seconds_per_step"] < 30
    timed = sum(row["seconds"] for name, row in stages.items() if name != "other")
    assert 0 < timed <= training["seconds_per_step"] * 1.001  # the stages are parts of the step
    assert stages["other"]["seconds"] >= -1e-9 and abs(sum(row["share"] for row in stages.values()) - 1) < 1e-6
    assert stages["data"]["items"] == stages["rays"]["items"] == report["rays_per_batch"]
    # Each pass keeps fewer samples: all march steps, the occupied ones, the lit ones.
    assert stages["march"]["items"] >= stages["density pass"]["items"] >= stages["field"]["items"] > 0
    # On this CPU the compiled training march does the density pass inside the march.
    assert training["compiled_march"] and stages["density pass"]["reference_seconds"] is None
    for name in ("march", "field", "backward", "optimiser"):
        row = stages[name]
        assert row["reference_seconds"] > 0 and row["times_reference"] == pytest.approx(
            row["seconds"] / row["reference_seconds"]), name
        # A lower bound on the stage's time at the machine's best measured rates (a margin for
        # the rates' own timing noise).
        assert row["times_reference"] > 0.8, (name, row)
    assert "Farthest from its limit" in result.stdout
    for part in (training, report["render"]):  # the hypervisor's share while each was timed (Linux)
        assert part["cpu_stolen_share"] is None or 0.0 <= part["cpu_stolen_share"] <= 1.0
    render = {row["stage"]: row for row in report["render"]["stages"]}
    # On this CPU the compiled march renders (spans, march and density in one pass).
    assert report["render"]["compiled_march"] and list(render) == ["march", "colour", "shade", "other"]
    assert render["march"]["items"] >= render["colour"]["items"] > 0
    # "shade": the rays given a colour; with deferred colour its network's FLOPs are its reference.
    assert 0 < render["shade"]["items"] <= report["image_size"][0] * report["image_size"][1]
    deferred = json.loads((out / "runs" / "auto" / "config.json").read_text())["config"]["grid"]["deferred_colour"]
    assert (render["shade"]["reference_seconds"] is not None) == deferred
    # Training's "composite" shades the rays with deferred colour: its network's FLOPs bound it.
    assert (stages["composite"]["reference_seconds"] is not None) == deferred
    if deferred:
        assert stages["composite"]["times_reference"] > 0.8
    assert "Through the compiled march" in result.stdout
    # Timed by default over whole periods of the occupancy refresh, at least 50 steps: each
    # refresh's cost is in the step as often as training pays it.
    every = training["occupancy_refresh_every"]
    assert report["warmup"]["iterations"] > 0 and every >= 1
    assert training["steps"] % every == 0 and 50 <= training["steps"] < 50 + every
    assert f"refreshed once in {every}" in result.stdout
    assert "## Training step" in result.stdout and "## Rendered view" in result.stdout



def test_bench_step_from_a_run_times_that_state_and_shows_an_earlier_profile_beside(tiny_demo_dataset,
                                                                                     trained_marched_run, tmp_path):
    """--from-run: no warm-up; the steps continue a copy of the run (its preset, from its
    iteration), the run itself untouched. --before: an earlier profile's stages beside this
    one's, from the same state; a file that is no profile is refused by name, before anything
    is written."""
    checkpoint = RunFolder(trained_marched_run).checkpoint_path
    untouched = checkpoint.read_bytes()
    refused = run_python("-m", "nerf_backend", "bench-step", str(tiny_demo_dataset), "--from-run",
                         str(trained_marched_run), "--out", str(tmp_path / "elsewhere"), check=False)
    assert refused.returncode != 0 and f"{trained_marched_run}: trained on " in refused.stderr
    assert not (tmp_path / "elsewhere").exists()  # refused before anything is written
    tiny_demo_dataset = Path(RunFolder(trained_marched_run).read_config()["dataset"])
    first, second = tmp_path / "first", tmp_path / "second"
    run_python("-m", "nerf_backend", "bench-step", str(tiny_demo_dataset), "--from-run", str(trained_marched_run),
               "--steps", "4", "--out", str(first))
    report = json.loads((first / "step_profile.json").read_text())
    assert report["preset"] == "fast" and report["training"]["steps"] == 4  # the run's preset, not the default
    assert report["warmup"] == {"iterations": 300, "seconds": pytest.approx(report["warmup"]["seconds"]),
                                "from_run": str(trained_marched_run.resolve())}
    assert checkpoint.read_bytes() == untouched
    result = run_python("-m", "nerf_backend", "bench-step", str(tiny_demo_dataset), "--from-run",
                        str(trained_marched_run), "--steps", "4", "--before", str(first / "step_profile.json"),
                        "--out", str(second))
    later = json.loads((second / "step_profile.json").read_text())
    assert later["before"]["training"] == report["training"] and later["before"]["render"] == report["render"]
    for row in later["training"]["stages"]:  # each stage's before, after and their ratio, in the page
        old = next(r for r in report["training"]["stages"] if r["stage"] == row["stage"])
        ratio = f"{row['seconds'] / old['seconds']:.2f}" if old["seconds"] > 0 else "—"
        expected = f"| {row['stage']} | {old['seconds'] * 1000:.2f} | {row['seconds'] * 1000:.2f} | {ratio} |"
        assert expected in result.stdout
    assert "Not side by side" not in result.stdout and result.stdout.count("| stage | before ms | after ms |") == 2
    not_a_profile = tmp_path / "not_a_profile.json"
    not_a_profile.write_text('{"preset": "fast"}')
    refused = run_python("-m", "nerf_backend", "bench-step", str(tiny_demo_dataset), "--from-run",
                         str(trained_marched_run), "--before", str(not_a_profile), "--out", str(tmp_path / "third"),
                         check=False)
    assert refused.returncode != 0 and f"{not_a_profile}: not a marched preset's bench-step profile" in refused.stderr
    assert not (tmp_path / "third").exists()


def test_a_profile_from_another_state_is_shown_beside_but_said_not_side_by_side():
    """before_and_after: profiles that started at another iteration or grid are not a before
    and after of the code; the page says so and how to make them one."""
    from nerf_backend.bench.step_profile import before_and_after

    def profile(iterations: int, vertices: list, march: float) -> dict:
        stages = [{"stage": "march", "seconds": march, "reference_seconds": march / 4, "times_reference": 4.0}]
        return {"commit": "abc1234", "warmup": {"iterations": iterations, "from_run": "/runs/ten"},
                "vertices": vertices,
                "training": {"seconds_per_step": 2 * march, "stages": stages},
                "render": {"seconds": 10 * march, "stages": stages}}

    report = profile(1000, [64, 64, 64], 0.003)
    report["before"] = profile(1000, [64, 64, 64], 0.004)
    lines = before_and_after(report, "training", "step")
    assert lines[0].startswith("Before (abc1234) and after (abc1234): 8.0 → 6.0 ms a step (0.75×)")
    # From the same start, both against this run's reference (0.75 ms): 4 ms is 5.3× it, 3 ms 4.0×.
    assert "| march | 4.00 | 3.00 | 0.75 | 5.3 | 4.0 |" in lines and not any("Not side by side" in l for l in lines)
    report["before"] = profile(900, [48, 48, 48], 0.004)
    lines = before_and_after(report, "render", "view")
    assert any(l.startswith("Not side by side: the before started at iteration 900") for l in lines)
    assert "| march | 4.00 | 3.00 | 0.75 | 4.0 | 4.0 |" in lines  # each against its own reference
    report["before"] = profile(1000, [64, 64, 64], 0.004)
    report["before"]["warmup"]["from_run"] = None  # the same count of steps, but from a warm-up of its own
    assert any(l.startswith("Not side by side") and "(from a warm-up)" in l for l in before_and_after(
        report, "training", "step"))

def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


def _variant_pid(run: Path) -> int:
    """The process training in ``run``: the one its lock names (started by the bench, directly or
    from its fork server)."""
    return int((run / LOCK_NAME).read_text())


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads child processes from /proc")
def test_stopping_bench_stops_the_variant_it_is_training(tiny_demo_dataset, tmp_path):
    out = tmp_path / "bench"
    bench = subprocess.Popen([sys.executable, "-m", "nerf_backend", "bench", str(tiny_demo_dataset), "--presets", "fast",
                              "--iters", "1000000", "--points", "1", "--out", str(out)], cwd=REPO_ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    events = out / "runs" / "fast" / "events.jsonl"
    deadline = time.monotonic() + 120
    while not (events.is_file() and '"train"' in events.read_text()):
        assert time.monotonic() < deadline and bench.poll() is None, "the variant never started training"
        time.sleep(0.3)
    # The variant's process (its run folder's lock names it) and every process the bench started.
    processes = [_variant_pid(out / "runs" / "fast"), *_children(bench.pid)]
    bench.send_signal(signal.SIGTERM)
    bench.wait(60)
    deadline = time.monotonic() + 60
    while any(Path(f"/proc/{pid}").exists() and "Z" not in Path(f"/proc/{pid}/stat").read_text().split()[2:3]
              for pid in processes):
        assert time.monotonic() < deadline, "the variant's process outlived the bench"
        time.sleep(0.3)


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads child processes from /proc")
def test_a_variant_process_that_dies_is_an_error_not_a_hang(tiny_demo_dataset, tmp_path):
    out = tmp_path / "bench"
    bench = subprocess.Popen([sys.executable, "-m", "nerf_backend", "bench", str(tiny_demo_dataset), "--presets", "fast",
                              "--iters", "1000000", "--points", "1", "--out", str(out)], cwd=REPO_ROOT,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    events = out / "runs" / "fast" / "events.jsonl"
    deadline = time.monotonic() + 120
    while not (events.is_file() and '"train"' in events.read_text()):
        assert time.monotonic() < deadline and bench.poll() is None, "the variant never started training"
        time.sleep(0.3)
    os.kill(_variant_pid(out / "runs" / "fast"), signal.SIGKILL)  # what the system's out-of-memory killer does
    _, stderr = bench.communicate(timeout=60)
    assert bench.returncode == 2
    assert "variant 'fast' failed: its process ended (exit code -9) without a result" in stderr
