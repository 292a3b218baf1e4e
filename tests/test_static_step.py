"""A mapping step with static shapes computes the step the dynamic decode does: the same loss, the same
gradient of every parameter and the same refinement statistics, on a real map's window (to float
rounding: the decoders run over more rows, so their sums round in another order)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from steady_step import mapped

from ogmapping.optim import refine
from ogmapping.structure.anchors import LEARNABLE

STATISTICS = ("grad_sum", "grad_count", "max_opacity", "observations")


def step_without_update(mapper, view, window, static_shapes: bool):
    """The loss, every parameter's gradient and the statistics of one step, its optimisers not stepped."""
    model = mapper.model
    model.profile = dataclasses.replace(model.profile, static_shapes=static_shapes)
    model.optimizer.zero_grad(set_to_none=True)
    if model.hash_optimizer is not None:
        model.hash_optimizer.zero_grad()
    model.anchors.reset_statistics()
    before = {name: getattr(model.anchors, name).clone() for name in STATISTICS}
    total, renders, _ = mapper.steps.objective(view, window)
    total.backward()
    accumulate = refine.accumulate_drawn if static_shapes else refine.accumulate
    for gaussians, output, drawn in renders:
        accumulate(model.anchors, gaussians, output.means2d.grad, output.visible, drawn.intrinsics.width,
                   drawn.intrinsics.height)
    count = len(model.anchors)
    named = [*((name, model.anchors.parameter(name)) for name in LEARNABLE), *model.decoders.named_parameters()]
    grads = {name: param.grad[:count] if name in LEARNABLE else param.grad for name, param in named
             if param.grad is not None}
    if model.hash_optimizer is not None:
        grads["hash table"] = model.encoding.gradients.dense(model.encoding.table.shape)
    statistics = {name: getattr(model.anchors, name).clone() for name in STATISTICS}
    for name, value in before.items():  # the next call starts from the same statistics
        setattr(model.anchors, name, value)
    return total.detach(), grads, statistics, renders


@pytest.mark.parametrize("preset", ["sparse", "dense"])
def test_static_shapes_step_as_the_dynamic_decode_does(preset: str) -> None:
    mapper, view, window = mapped(preset, {}, shared_decode=True)
    mapper.model.profile = dataclasses.replace(mapper.profile, compiled=False)
    loss, grads, statistics, renders = step_without_update(mapper, view, window, static_shapes=False)
    static_loss, static_grads, static_statistics, static_renders = step_without_update(mapper, view, window,
                                                                                      static_shapes=True)
    torch.testing.assert_close(static_loss, loss, rtol=1e-5, atol=0)
    assert static_grads.keys() == grads.keys() and "offsets" in grads
    for name, grad in grads.items():
        torch.testing.assert_close(static_grads[name], grad, rtol=1e-4, atol=1e-6, msg=name)
    for name, value in statistics.items():
        torch.testing.assert_close(static_statistics[name], value, rtol=1e-4, atol=1e-6, msg=name)
    assert statistics["grad_count"].sum() > 0
    for (gaussians, output, _), (static, static_output, _) in zip(renders, static_renders, strict=True):
        assert int(static.drawn_count()) == len(gaussians)
        torch.testing.assert_close(static_output.color, output.color, rtol=1e-5, atol=1e-6)
