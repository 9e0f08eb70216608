"""RowSparseAdam (training/sparse_adam.py, kernels/vm_grid.c's sparse_adam) against references
written here: PyTorch's Adam where a step touches every row, and the masked-Adam rule (rows a
step left keep their values; their moments decay by β^k for the k steps they skipped) where it
touches some. Tolerances: float32 rounding over a few steps (1e-6 absolute on values of order
0.1)."""

from __future__ import annotations

import pytest
import torch

from nerf_backend.field_components import compiled_grid
from nerf_backend.field_components.grid_encodings import VectorMatrixGrid
from nerf_backend.training.sparse_adam import RowSparseAdam

BETAS, EPS, LR = (0.9, 0.99), 1e-15, 0.01


@pytest.fixture(scope="module", autouse=True)
def library():
    if compiled_grid.compiled_grid_library() is None:
        pytest.skip("no C compiler here: every parameter takes PyTorch's dense Adam")


def _pair(seed: int = 0) -> tuple[VectorMatrixGrid, VectorMatrixGrid]:
    torch.manual_seed(seed)
    first = VectorMatrixGrid(8, (9, 7, 5))
    second = VectorMatrixGrid(8, (9, 7, 5))
    second.load_state_dict(first.state_dict())
    return first, second


def test_touching_every_row_is_pytorchs_adam():
    sparse_grid, dense_grid = _pair()
    sparse = RowSparseAdam([{"params": list(sparse_grid.parameters()), "lr": LR}], grids=[sparse_grid], betas=BETAS,
                           eps=EPS)
    dense = torch.optim.Adam(dense_grid.parameters(), lr=LR, betas=BETAS, eps=EPS)
    x = torch.rand(4000, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    for _ in range(6):
        for grid, optimiser in ((sparse_grid, sparse), (dense_grid, dense)):
            optimiser.zero_grad(set_to_none=True)
            (grid(x) ** 2).sum().backward()
            optimiser.step()
    assert sparse.rows_updated == 9 * 7 + 9 * 5 + 7 * 5 + 5 + 7 + 9  # every row of every plane and line
    for a, b in zip(sparse_grid.parameters(), dense_grid.parameters()):
        assert float((a - b).detach().abs().max()) < 1e-6


def _masked_adam_reference(rows: torch.Tensor, gradients: list[torch.Tensor], touched: list[torch.Tensor]):
    """The rule, written plainly over [rows, width] tables: touched rows take Adam's update with
    moments decayed for the steps they skipped; others are left as they are."""
    rows = rows.clone()
    m, v = torch.zeros_like(rows), torch.zeros_like(rows)
    last = torch.zeros(rows.shape[0])
    for step, (gradient, mask) in enumerate(zip(gradients, touched), start=1):
        skipped = (step - last - 1)[:, None]
        new_m = BETAS[0] * (BETAS[0] ** skipped) * m + (1 - BETAS[0]) * gradient
        new_v = BETAS[1] * (BETAS[1] ** skipped) * v + (1 - BETAS[1]) * gradient ** 2
        update = LR / (1 - BETAS[0] ** step) * new_m / ((new_v.sqrt() / (1 - BETAS[1] ** step) ** 0.5) + EPS)
        m = torch.where(mask[:, None], new_m, m)
        v = torch.where(mask[:, None], new_v, v)
        rows = torch.where(mask[:, None], rows - update, rows)
        last = torch.where(mask, torch.full_like(last, step), last)
    return rows


def test_rows_a_step_leaves_keep_their_values_and_decay_their_moments_when_next_touched():
    grid, _ = _pair(seed=2)
    start = compiled_grid.channel_rows(grid.planes[0]).detach().clone()
    optimiser = RowSparseAdam([{"params": list(grid.parameters()), "lr": LR}], grids=[grid], betas=BETAS, eps=EPS)
    # Points at two corners, then the centre, then a corner again: each step touches some rows.
    batches = [torch.tensor([[-1.0, -1.0, 0.1]]), torch.tensor([[0.9, 0.9, 0.1]]), torch.tensor([[0.0, 0.0, 0.1]]),
               torch.tensor([[-1.0, -1.0, 0.1]])]
    gradients, touched = [], []
    for x in batches:
        optimiser.zero_grad(set_to_none=True)
        grid(x).sum().backward()
        sink = grid.row_gradients
        gradients.append(sink.gradients[0].detach().clone())
        touched.append(sink.marks[0].bool().clone())
        optimiser.step()
        assert int(sink.marks[0].sum()) == 0 and float(sink.gradients[0].abs().max()) == 0.0  # left clean
    expected = _masked_adam_reference(start, [compiled_grid.channel_rows(g) for g in gradients], touched)
    assert int(touched[0].sum()) == 4 and not bool((touched[0] & touched[1]).any())
    assert float((compiled_grid.channel_rows(grid.planes[0]).detach() - expected).abs().max()) < 1e-6
    untouched = ~torch.stack(touched).any(dim=0)
    assert torch.equal(compiled_grid.channel_rows(grid.planes[0]).detach()[untouched], start[untouched])


@pytest.mark.parametrize("threads", [2, 3])
def test_threads_share_the_rows_and_give_one_threads_values(threads, monkeypatch):
    """Planes of 12 000 and 10 800 rows (the kernel splits rows over threads from 4 096 a thread
    on), points that touch rows in every share: each thread count leaves the same values, bit
    for bit (a row's update is its own)."""
    torch.manual_seed(4)
    grids = [VectorMatrixGrid(8, (120, 100, 90)) for _ in range(2)]
    grids[1].load_state_dict(grids[0].state_dict())
    start = grids[0].planes[0].detach().clone()
    counts = []
    for grid, count in zip(grids, (1, threads)):
        monkeypatch.setattr(torch, "get_num_threads", lambda count=count: count)
        optimiser = RowSparseAdam([{"params": list(grid.parameters()), "lr": LR}], grids=[grid], betas=BETAS, eps=EPS)
        generator = torch.Generator().manual_seed(5)
        for _ in range(4):
            optimiser.zero_grad(set_to_none=True)
            (grid(torch.rand(3000, 3, generator=generator) * 2 - 1) ** 2).sum().backward()
            optimiser.step()
        counts.append(optimiser.rows_updated)
    assert counts[0] == counts[1] and counts[0] > 10_000
    for a, b in zip(grids[0].parameters(), grids[1].parameters()):
        assert torch.equal(a, b)
    assert float((grids[0].planes[0].detach() - start).abs().max()) > 1e-3  # the steps moved them


def test_a_grown_grid_trains_through_autograd_until_a_new_optimiser_attaches():
    """The trainer makes a new optimiser when the grid grows; until then the old buffers do not
    fit the new parameters, and the gradient goes to .grad (never into the old buffers)."""
    grid, _ = _pair(seed=3)
    RowSparseAdam([{"params": list(grid.parameters()), "lr": LR}], grids=[grid])
    grid.resize((11, 9, 7))
    grid(torch.zeros(5, 3)).sum().backward()
    assert all(p.grad is not None for p in grid.parameters())
    # An optimiser over the grown parameters whose buffers were made for others steps them densely.
    stale = RowSparseAdam([{"params": list(grid.parameters()), "lr": LR}], grids=[])
    stale._sparse = {id(p): (grid.row_gradients, i) for i, p in enumerate(
        [p for pair in zip(grid.planes, grid.lines) for p in pair])}
    before = [p.detach().clone() for p in grid.parameters()]
    stale.step()
    assert all(not torch.equal(a, b) for a, b in zip(before, grid.parameters()))
    grid.zero_grad(set_to_none=True)
    optimiser = RowSparseAdam([{"params": list(grid.parameters()), "lr": LR}], grids=[grid])
    optimiser.zero_grad(set_to_none=True)
    grid(torch.zeros(5, 3)).sum().backward()
    assert all(p.grad is None for p in grid.parameters())
    optimiser.step()
    assert optimiser.rows_updated == 2 * 6 + 2 * 3  # 4 plane rows and 2 line rows of each of 3 components


def test_a_checkpoint_round_trip_continues_the_same_steps(tmp_path):
    """state_dict / load_state_dict keep the moments, the step and each row's last step."""
    first, second = _pair(seed=4)
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(5)) * 2 - 1
    optimisers = [RowSparseAdam([{"params": list(g.parameters()), "lr": LR}], grids=[g]) for g in (first, second)]
    for _ in range(3):
        for grid, optimiser in zip((first, second), optimisers):
            optimiser.zero_grad(set_to_none=True)
            (grid(x[:100]) ** 2).sum().backward()
            optimiser.step()
    torch.save(optimisers[1].state_dict(), tmp_path / "optimiser.pt")
    restored = RowSparseAdam([{"params": list(second.parameters()), "lr": LR}], grids=[second])
    restored.load_state_dict(torch.load(tmp_path / "optimiser.pt", weights_only=True))
    for grid, optimiser in ((first, optimisers[0]), (second, restored)):
        optimiser.zero_grad(set_to_none=True)
        (grid(x[100:]) ** 2).sum().backward()
        optimiser.step()
    for a, b in zip(first.parameters(), second.parameters()):
        assert float((a - b).detach().abs().max()) < 1e-7


def test_what_is_kept_of_a_grids_values_is_made_again_after_a_sparse_step():
    """The kernel writes the rows through a pointer; the step moves each parameter's version on,
    so a cache keyed on the values (``kept_derived``: the half tables, the dense density) is made
    again. Without it, training's validations rendered lego through the first validation's half
    tables (about 20 dB where the run scored 35.5)."""
    from nerf_backend.core.tensor_keys import kept_derived
    grid, _ = _pair()
    optimiser = RowSparseAdam([{"params": list(grid.parameters()), "lr": LR}], grids=[grid], betas=BETAS, eps=EPS)

    def kept():
        return kept_derived(grid, "copies", list(grid.parameters()), lambda: [p.detach().clone() for p in grid.parameters()])

    before = kept()
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(2)) * 2 - 1
    (grid(x) ** 2).sum().backward()
    optimiser.step()
    assert optimiser.rows_updated > 0 and all(p.grad is None for p in grid.parameters())  # the kernel's step
    after = kept()
    assert after is not before
    assert all(torch.equal(copy, p) for copy, p in zip(after, grid.parameters()))
    assert any(not torch.equal(old, new) for old, new in zip(before, after))
