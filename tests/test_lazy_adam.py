"""Lazy Adam over a hash table's touched rows, checked against torch.optim.Adam."""

import pytest
import torch

from ogmapping.model.row_gradients import RowGradients, SparseRowGather
from ogmapping.optim.lazy_adam import LazyAdam


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


@pytest.mark.parametrize(("compiled", "static_shapes"), [(True, False), (False, False), (False, True)],
                         ids=["compiled", "torch-ops", "static-shapes"])
def test_steps_equal_torch_adam_when_every_row_is_touched(compiled, static_shapes):
    torch.manual_seed(0)
    start = torch.randn(2, 4, 3)
    lazy_table = torch.nn.Parameter(start.clone())
    dense_table = torch.nn.Parameter(start.clone())
    sink = RowGradients()
    lazy = LazyAdam(lazy_table, sink, lr=0.01, compiled=compiled, static_shapes=static_shapes)
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


def _lookups(levels: int, size: int, count: int, seed: int) -> tuple:
    """Random hash-encoding lookups: flat rows (count, levels, 8) inside each level, weights, feature gradients."""
    generator = torch.Generator().manual_seed(seed)
    rows = torch.randint(0, size, (count, levels, 8), generator=generator) + torch.arange(levels).view(1, -1, 1) * size
    weights = torch.rand(count, levels, 8, generator=generator)
    grad = torch.randn(count, levels * 2, generator=generator)
    return rows, weights, grad


def _as_pairs(rows: torch.Tensor, weights: torch.Tensor, grad: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    levels = rows.shape[1]
    values = grad.view(-1, levels, 1, 2) * weights.unsqueeze(-1)  # (count, levels, 8, F)
    return rows.reshape(-1), values.reshape(-1, 2)


def test_lookups_summed_in_place_equal_the_same_pairs_summed_by_sort():
    shape = torch.Size((3, 64, 2))
    in_place, by_pairs = RowGradients(), RowGradients()
    for seed in range(2):  # two views' backward passes into one step
        rows, weights, grad = _lookups(3, 64, 40, seed)
        in_place.accumulate_lookups(shape, rows.numpy(), weights.numpy(), grad.numpy())
        by_pairs.add(*_as_pairs(rows, weights, grad))
    torch.testing.assert_close(in_place.dense(shape), by_pairs.dense(shape))
    assert in_place.touched.counts.sum() == len(by_pairs.summed()[0])
    in_place.clear()
    assert in_place.summed() is None
    assert not in_place.touched.values.any() and not in_place.touched.flags.any()


def test_compiled_step_over_lookups_equals_the_torch_step_and_leaves_the_buffer_empty():
    shape = torch.Size((3, 64, 2))
    start = torch.randn(shape)
    compiled_table, torch_table = torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())
    in_place, by_pairs = RowGradients(), RowGradients()
    compiled = LazyAdam(compiled_table, in_place, lr=0.01, compiled=True)
    reference = LazyAdam(torch_table, by_pairs, lr=0.01, compiled=False)
    for seed in range(4):
        compiled.zero_grad()
        reference.zero_grad()
        rows, weights, grad = _lookups(3, 64, 30, seed)
        in_place.accumulate_lookups(shape, rows.numpy(), weights.numpy(), grad.numpy())
        by_pairs.add(*_as_pairs(rows, weights, grad))
        compiled.step()
        reference.step()
        assert not in_place.touched.values.any() and not in_place.touched.flags.any()
    torch.testing.assert_close(compiled_table, torch_table)
    torch.testing.assert_close(compiled.exp_avg_sq, reference.exp_avg_sq)
    assert compiled.step_count == reference.step_count == 4


def test_the_static_shape_step_over_the_whole_table_equals_the_step_over_the_touched_rows():
    shape = torch.Size((3, 256, 2))
    start = torch.randn(shape)
    masked_table, torch_table = torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())
    masked_sink, sink = RowGradients(), RowGradients()
    masked = LazyAdam(masked_table, masked_sink, lr=0.01, compiled=False, static_shapes=True)
    reference = LazyAdam(torch_table, sink, lr=0.01, compiled=False)
    for seed in range(4):
        masked.zero_grad()
        reference.zero_grad()
        for view in range(2):  # two views' backward passes into one step, a few rows in both
            pairs = _as_pairs(*_lookups(3, 256, 3, 10 * seed + view))
            masked_sink.add(*pairs)
            sink.add(*pairs)
        masked.step()
        reference.step()
    torch.testing.assert_close(masked_table, torch_table)
    torch.testing.assert_close(masked.exp_avg, reference.exp_avg)
    torch.testing.assert_close(masked.exp_avg_sq, reference.exp_avg_sq)
    untouched = reference.exp_avg.view(-1, 2).eq(0).all(1)
    assert untouched.any() and torch.equal(masked_table.detach().view(-1, 2)[untouched], start.view(-1, 2)[untouched])


def test_a_buffer_is_for_one_table_shape():
    sink = RowGradients()
    rows, weights, grad = _lookups(3, 64, 5, 0)
    sink.accumulate_lookups(torch.Size((3, 64, 2)), rows.numpy(), weights.numpy(), grad.numpy())
    with pytest.raises(ValueError, match="gradient buffer"):
        sink.accumulate_lookups(torch.Size((3, 32, 2)), rows.numpy(), weights.numpy(), grad.numpy())
