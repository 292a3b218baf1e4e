"""Lazy Adam over a hash table's touched rows, checked against torch.optim.Adam."""

import pytest
import torch

from ogmapping.lazy_adam import LazyAdam, RowGradients, SparseRowGather


def test_gather_matches_indexing_and_deposits_its_gradient_rows():
    table = torch.randn(3, 5, 2, requires_grad=True)
    rows = torch.tensor([0, 7, 7, 14, 3])
    sink = RowGradients()
    out = SparseRowGather.apply(table, rows, sink)
    assert torch.equal(out, table.detach().view(-1, 2)[rows])
    weights = torch.randn_like(out)
    (out * weights).sum().backward()
    assert table.grad is None, "the gradient goes to the sink, not to a dense tensor"
    expected = torch.zeros(15, 2).index_add_(0, rows, weights).view(3, 5, 2)
    assert torch.allclose(sink.dense(table.shape), expected)
    unique_rows, summed = sink.summed()
    assert unique_rows.tolist() == [0, 3, 7, 14]
    assert torch.allclose(summed[2], weights[1] + weights[2])


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch-ops"])
def test_steps_equal_torch_adam_when_every_row_is_touched(compiled):
    torch.manual_seed(0)
    start = torch.randn(2, 4, 3)
    lazy_table = torch.nn.Parameter(start.clone())
    dense_table = torch.nn.Parameter(start.clone())
    sink = RowGradients()
    lazy = LazyAdam(lazy_table, sink, lr=0.01, compiled=compiled)
    dense = torch.optim.Adam([dense_table], lr=0.01, eps=1e-15)
    every_row = torch.arange(8).repeat(2)
    for _ in range(5):
        target = torch.randn(16, 3)
        lazy.zero_grad()
        dense.zero_grad()
        ((SparseRowGather.apply(lazy_table, every_row, sink) - target) ** 2).sum().backward()
        ((dense_table.view(-1, 3)[every_row] - target) ** 2).sum().backward()
        lazy.step()
        dense.step()
    assert torch.allclose(lazy_table, dense_table, atol=1e-6)


def test_untouched_rows_keep_their_values_and_moments():
    table = torch.nn.Parameter(torch.randn(1, 6, 2))
    before = table.detach().clone()
    sink = RowGradients()
    optimizer = LazyAdam(table, sink, lr=0.1, compiled=True)
    touched = torch.tensor([1, 4])
    SparseRowGather.apply(table, touched, sink).sum().backward()
    optimizer.step()
    untouched = torch.tensor([0, 2, 3, 5])
    assert torch.equal(table.detach()[0, untouched], before[0, untouched])
    assert not torch.equal(table.detach()[0, touched], before[0, touched])
    assert torch.count_nonzero(optimizer.exp_avg[0, untouched]) == 0
    optimizer.zero_grad()
    optimizer.step()
    assert optimizer.step_count == 1, "a step with no gradient rows changes nothing"
