"""KiloNeRF measured for the live view (issue 42): the grid of tiny networks evaluated as one
grouped product a layer, checked against each sample's own cell's layer; a real run distilled
and both models rendered through the same march by ``bench-kilonerf``."""

from __future__ import annotations

import json

import torch
from conftest import run_python

from nerf_backend.field_components.cell_networks import BLOCK, CellLinear, pack_by_cell


def test_each_sample_goes_through_its_own_cells_layer():
    torch.manual_seed(0)
    cells, samples = 7, 3 * BLOCK + 5  # cells of zero, one and several blocks
    cell = torch.cat([torch.zeros(2 * BLOCK + 3, dtype=torch.long), torch.randint(1, 5, (samples - 2 * BLOCK - 3,))])
    cell = cell[torch.randperm(samples)]
    layer = CellLinear(cells, 5, 4)
    x = torch.randn(samples, 5)
    packing = pack_by_cell(cell, cells)
    grouped = packing.unpack(layer(packing.pack(x), packing))
    reference = torch.einsum("pi,pio->po", x, layer.weight[cell]) + layer.bias[cell]
    torch.testing.assert_close(grouped, reference, rtol=1e-5, atol=1e-5)
    assert packing.rows % BLOCK == 0 and packing.rows < samples + cells * BLOCK


def test_bench_kilonerf_distils_a_run_and_renders_both_through_the_same_march(trained_marched_run, tmp_path):
    result = run_python("-m", "nerf_backend", "bench-kilonerf", str(trained_marched_run), "--seconds", "15",
                        "--views", "2", "--cells", "4,4,4", "--device", "cpu", "--out", str(tmp_path / "kilo"))
    report = json.loads((tmp_path / "kilo" / "kilonerf.json").read_text())
    models = report["models"]
    teacher, same_march, student = (models[name] for name in ("the run's model, the product's renderer",
                                                               "the run's model, PyTorch's march", "KiloNeRF"))
    assert abs(same_march["psnr"] - teacher["psnr"]) < 0.5  # the same model through either march
    print(f"tiny demo 40×40, 15 s of distillation: teacher {teacher['psnr']:.2f} dB, KiloNeRF {student['psnr']:.2f} dB")
    assert report["cells"] == [4, 4, 4] and report["distillation"]["steps"] > 0
    # A KiloNeRF that learnt nothing renders the empty box: about 10 dB on the demo's views.
    assert student["psnr"] > 18.0 and student["psnr"] <= teacher["psnr"] + 1.0, (teacher, student)
    assert student["full_seconds"] > 0 and student["quarter_seconds"] > 0 and student["bytes"] > 0
    assert "| KiloNeRF |" in result.stdout


def test_bench_kilonerf_refuses_a_model_it_cannot_march(trained_run, tmp_path):
    result = run_python("-m", "nerf_backend", "bench-kilonerf", str(trained_run), "--seconds", "1", "--out",
                        str(tmp_path / "kilo"), check=False)
    assert result.returncode != 0 and "bench-kilonerf distils a marched model" in result.stderr, result.stderr


def test_no_samples_give_no_rows():
    """A chunk whose rays all miss the occupied cells asks for nothing (it happened rendering lego)."""
    layer = CellLinear(3, 5, 4)
    packing = pack_by_cell(torch.zeros(0, dtype=torch.long), 3)
    assert packing.unpack(layer(packing.pack(torch.zeros(0, 5)), packing)).shape == (0, 4)
