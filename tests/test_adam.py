"""The project's Adam (nerf_backend/training/adam.py) against torch.optim.Adam: the same update,
fused and textbook, the same checkpoint layout both ways, and a training process that never
imports torch._dynamo (the reason it exists)."""

from __future__ import annotations

import pytest
import torch
from conftest import run_python

from nerf_backend.training import adam as adam_module
from nerf_backend.training.adam import Adam

BETAS, EPS = (0.9, 0.99), 1e-15


def _parameters(seed: int) -> list[torch.nn.Parameter]:
    generator = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(shape, generator=generator)) for shape in ((7, 3), (5,), (2, 4, 3))]


def _groups(parameters, rates=(1e-2, 3e-3)) -> list[dict]:
    return [{"params": parameters[:2], "lr": rates[0], "initial_lr": rates[0]},
            {"params": parameters[2:], "lr": rates[1], "initial_lr": rates[1]}]


def _run(optimiser, parameters, steps: range) -> None:
    """Steps of made-up gradients, each step's its own; the second parameter has none on odd
    steps (a parameter a step left alone keeps its value and its moments)."""
    for step in steps:
        generator = torch.Generator().manual_seed(1000 + step)
        for index, parameter in enumerate(parameters):
            gradient = torch.randn(parameter.shape, generator=generator) * 10.0 ** (index - 1)
            parameter.grad = None if (index == 1 and step % 2) else gradient
        optimiser.step()
        optimiser.zero_grad(set_to_none=True)


@pytest.mark.parametrize("textbook", [False, True], ids=["fused", "textbook"])
def test_steps_equal_torchs_adam(textbook, monkeypatch):
    if textbook:  # as on a device without the fused kernel
        monkeypatch.setattr(adam_module, "_unfused", {"cpu"})
    ours, theirs = _parameters(0), _parameters(0)
    _run(Adam(_groups(ours), betas=BETAS, eps=EPS), ours, range(6))
    _run(torch.optim.Adam(_groups(theirs), betas=BETAS, eps=EPS, fused=True), theirs, range(6))
    for mine, reference in zip(ours, theirs):
        # Measured here: both equal to the last bit (other CPUs may round the textbook one apart).
        torch.testing.assert_close(mine.detach(), reference.detach(), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("textbook", [False, True], ids=["fused", "textbook"])
def test_a_step_moves_each_updated_parameters_version_on(textbook, monkeypatch):
    """What is kept of a parameter's values (``tensor_keys.kept_derived``: the compiled shading's
    folded weights) is keyed on its version; the fused kernel leaves the counter alone, so the
    step moves it on. Without it, training's validations shaded with the first validation's
    network (lego at 800×800: 23.94 dB where the same weights rendered afresh scored 24.47)."""
    if textbook:
        monkeypatch.setattr(adam_module, "_unfused", {"cpu"})
    parameters = _parameters(0)
    before = [p._version for p in parameters]
    _run(Adam(_groups(parameters), betas=BETAS, eps=EPS), parameters, range(1))
    assert all(p._version > v for p, v in zip(parameters, before))


def test_checkpoints_load_both_ways_and_continue_as_one_run():
    """A run's checkpoint of torch's Adam (every run before this module) resumes here and the
    other way round, as one uninterrupted run would go on."""
    straight = _parameters(0)
    _run(torch.optim.Adam(_groups(straight), betas=BETAS, eps=EPS, fused=True), straight, range(8))

    first = _parameters(0)
    torch_adam = torch.optim.Adam(_groups(first), betas=BETAS, eps=EPS, fused=True)
    _run(torch_adam, first, range(3))
    second = [torch.nn.Parameter(p.detach().clone()) for p in first]
    ours = Adam(_groups(second, rates=(0.5, 0.5)), betas=(0.5, 0.5), eps=1.0)  # the saved settings win
    ours.load_state_dict(torch_adam.state_dict())
    assert [g["lr"] for g in ours.param_groups] == [1e-2, 3e-3] and ours.param_groups[0]["betas"] == BETAS
    _run(ours, second, range(3, 5))
    third = [torch.nn.Parameter(p.detach().clone()) for p in second]
    back = torch.optim.Adam(_groups(third), betas=BETAS, eps=EPS, fused=True)
    back.load_state_dict(ours.state_dict())
    _run(back, third, range(5, 8))
    for resumed, reference in zip(third, straight):
        torch.testing.assert_close(resumed.detach(), reference.detach(), rtol=1e-6, atol=1e-7)


def test_a_state_for_other_groups_is_refused():
    ours = Adam(_groups(_parameters(0)))
    with pytest.raises(ValueError, match="other parameter groups"):
        ours.load_state_dict({"state": {}, "param_groups": [{"params": [0, 1, 2], "lr": 1.0}]})


def test_a_training_process_never_imports_dynamo(tiny_demo_dataset, tmp_path):
    """torch.optim's first use imports torch._dynamo (0.9-2 s a process): a training, its
    checkpoint and its resume go without it."""
    script = ("import sys\nfrom nerf_backend.cli import main\n"
              f"assert main(['train', {str(tiny_demo_dataset)!r}, '--out', {str(tmp_path / 'run')!r}, '--preset',"
              " 'fast', '--iters', '3', '--no-progress']) == 0\n"
              f"assert main(['train', {str(tiny_demo_dataset)!r}, '--out', {str(tmp_path / 'run')!r}, '--resume',"
              " '--iters', '5', '--no-progress']) == 0\n"
              "print('dynamo' if 'torch._dynamo' in sys.modules else 'no dynamo')\n")
    result = run_python("-c", script)
    assert result.stdout.strip().splitlines()[-1] == "no dynamo", result.stdout + result.stderr
