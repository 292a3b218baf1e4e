"""Selective Adam against torch's Adam on the visible rows only, values and moments."""

from __future__ import annotations

import pytest
import torch

from ogmapping.optim.selective_adam import SelectiveAdam, moved
from ogmapping.structure.anchors import LEARNABLE, AnchorMap

BETAS, EPS = (0.9, 0.999), 1e-15


def reference_step(param: torch.Tensor, state: dict, grad: torch.Tensor, visible: torch.Tensor,
                   lr: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """torch's single-tensor Adam on the rows of ``visible`` alone, from their moments and the step count of
    ``state`` (before the step): (values, exp_avg, exp_avg_sq) of those rows after it."""
    rows = torch.nn.Parameter(param.detach()[visible].clone())
    adam = torch.optim.Adam([rows], lr=lr, betas=BETAS, eps=EPS, foreach=False, fused=False)
    if state:
        adam.state[rows] = {"step": state["step"].clone(), "exp_avg": state["exp_avg"][visible].clone(),
                            "exp_avg_sq": state["exp_avg_sq"][visible].clone()}
    rows.grad = grad[visible].clone()
    adam.step()
    after = adam.state[rows]
    return rows.detach(), after["exp_avg"], after["exp_avg_sq"]


def random_rows(generator: torch.Generator, shape: tuple[int, ...]) -> torch.nn.Parameter:
    return torch.nn.Parameter(torch.randn(*shape, generator=generator))


@pytest.mark.parametrize("shape", [(40, 3), (40, 5, 3)])
def test_visible_rows_step_as_adam_on_them_alone_and_the_others_keep_values_and_moments(shape):
    generator = torch.Generator().manual_seed(0)
    param = random_rows(generator, shape)
    adam = SelectiveAdam([{"params": [param], "lr": 0.05, "name": "rows"}], row_groups=["rows"], betas=BETAS, eps=EPS)
    for step in range(6):
        grad = torch.randn(shape, generator=generator)
        visible = torch.rand(shape[0], generator=generator) < 0.6
        before = param.detach().clone()
        state = {key: value.clone() for key, value in adam.state[param].items()}
        expected = reference_step(param, state, grad, visible, lr=0.05)
        param.grad = grad.clone()
        adam.select(visible)
        adam.step()
        after = adam.state[param]
        assert int(after["step"]) == step + 1
        for got, want in zip((param.detach(), after["exp_avg"], after["exp_avg_sq"]), expected, strict=True):
            assert torch.equal(got[visible], want)
        assert torch.equal(param.detach()[~visible], before[~visible])
        for key in ("exp_avg", "exp_avg_sq"):
            unseen = state[key][~visible] if state else torch.zeros_like(before[~visible])
            assert torch.equal(after[key][~visible], unseen)


def test_without_a_selection_and_in_other_groups_it_is_torch_adam():
    generator = torch.Generator().manual_seed(1)
    rows, weights = random_rows(generator, (16, 3)), random_rows(generator, (4, 4))
    twins = [torch.nn.Parameter(tensor.detach().clone()) for tensor in (rows, weights)]

    def groups(first, second):
        return [{"params": [first], "lr": 0.1, "name": "rows"}, {"params": [second], "lr": 0.01, "name": "mlp"}]

    selective = SelectiveAdam(groups(rows, weights), row_groups=["rows"], betas=BETAS, eps=EPS)
    adam = torch.optim.Adam(groups(*twins), betas=BETAS, eps=EPS)
    for step in range(4):
        grads = [torch.randn(16, 3, generator=generator), torch.randn(4, 4, generator=generator)]
        for param, grad in zip((rows, weights, *twins), grads * 2, strict=True):
            param.grad = grad.clone()
        if step % 2:  # every row visible: the same as no selection
            selective.select(torch.ones(16, dtype=torch.bool))
        selective.step()
        adam.step()
        assert torch.equal(rows, twins[0]) and torch.equal(weights, twins[1])
    assert rows.grad is not None  # the step hands the row groups' gradients back


def test_the_count_on_the_device_takes_torch_capturable_formula():
    """The branch for a step count the host never reads (CUDA's fused Adam keeps it on the device), run on
    CPU tensors: within rounding of the host's branch."""
    generator = torch.Generator().manual_seed(2)
    param, first, second = torch.randn(8, 3, generator=generator), torch.randn(8, 3, generator=generator), \
        torch.rand(8, 3, generator=generator)
    group = {"betas": BETAS, "lr": 0.02, "eps": 1e-8}
    step = torch.tensor(3.0)
    host = moved(param, first, second, step, group, host=True)
    torch.testing.assert_close(moved(param, first, second, step, group, host=False), host, rtol=1e-6, atol=1e-7)
    assert not torch.equal(host, param)


def test_fused_on_the_cpu_as_static_shapes_use_it():
    generator = torch.Generator().manual_seed(3)
    param = random_rows(generator, (24, 3))
    adam = SelectiveAdam([{"params": [param], "lr": 0.05, "name": "rows"}], row_groups=["rows"], betas=BETAS, eps=EPS,
                         fused=True)
    grad, visible = torch.randn(24, 3, generator=generator), torch.arange(24) % 3 == 0
    expected, _, _ = reference_step(param, {}, grad, visible, lr=0.05)
    before = param.detach().clone()
    param.grad = grad
    adam.select(visible)
    adam.step()
    torch.testing.assert_close(param.detach()[visible], expected)
    assert torch.equal(param.detach()[~visible], before[~visible])


def test_the_anchor_buffers_inert_rows_stay_inert():
    """Rows past the live count have zero values and moments; never visible, they keep them through steps and
    a capacity doubling, while live rows seen update."""
    anchors = AnchorMap(n_offsets=4, feature_dim=8, with_features=True, device=torch.device("cpu"), capacity=16)
    groups = [{"params": [anchors.parameter(name)], "lr": 0.01, "name": name} for name in LEARNABLE]
    adam = SelectiveAdam(groups, row_groups=LEARNABLE, betas=BETAS, eps=EPS)
    generator = torch.Generator().manual_seed(4)

    def add(count: int) -> None:
        codes = torch.arange(len(anchors), len(anchors) + count)
        anchors.add(codes, torch.zeros(count, dtype=torch.int64), torch.rand(count, 3, generator=generator),
                    torch.full((count,), 0.1), torch.randn(count, 8, generator=generator), adam)

    def step() -> None:
        visible = anchors.live & (torch.rand(anchors.capacity, generator=generator) < 0.5)
        visible[0] = True
        for name in LEARNABLE:
            param = anchors.parameter(name)
            param.grad = torch.randn(param.shape, generator=generator) * anchors.live.view(-1, *[1] * (param.dim() - 1))
        adam.select(visible)
        adam.step()

    add(10)
    for _ in range(3):
        step()
    add(20)  # past the capacity: the buffers and moments double
    step()
    assert anchors.capacity == 32
    for name in ("log_scales", "offsets", "features"):
        param = anchors.parameter(name)
        state = adam.state[param]
        for tensor in (param.detach(), state["exp_avg"], state["exp_avg_sq"]):
            assert not tensor[len(anchors):].any(), name
        assert state["exp_avg"][0].any(), name
