"""The static-shape step as compiled graphs (``ogmapping.mapping.graphs``, Inductor on the CPU): the same
step as its eager definition, with no graph break (each part is compiled whole, ``fullgraph``), and no
recompilation while the map grows and is pruned, its buffers' capacity doubling included."""

from __future__ import annotations

import pytest
import torch
from steady_step import mapped
from test_static_step import step_without_update

from ogmapping.mapping.graphs import StepGraphs
from ogmapping.runtime.threads import torch_threads


@pytest.mark.parametrize("preset", ["sparse", "dense"])
def test_the_compiled_step_equals_the_eager_one(preset: str) -> None:
    mapper, view, window = mapped(preset, {}, step="static")
    model = mapper.model
    torch._dynamo.reset()  # compiled here for these shapes, whatever other tests compiled before
    with torch_threads(mapper.profile.threads):
        loss, grads, statistics, renders = step_without_update(mapper, view, window, static_shapes=True)
        model.graphs = StepGraphs.build(compiled=True, device=model.device)
        compiled = step_without_update(mapper, view, window, static_shapes=True)
    compiled_loss, compiled_grads, compiled_statistics, compiled_renders = compiled
    torch.testing.assert_close(compiled_loss, loss, rtol=1e-4, atol=0)
    assert compiled_grads.keys() == grads.keys()
    for name, grad in grads.items():
        torch.testing.assert_close(compiled_grads[name], grad, rtol=1e-4, atol=1e-6, msg=name)
    for name, value in statistics.items():
        torch.testing.assert_close(compiled_statistics[name], value, rtol=1e-4, atol=1e-6, msg=name)
    for (_, output, _), (_, compiled_output, _) in zip(renders, compiled_renders, strict=True):
        torch.testing.assert_close(compiled_output.color, output.color, rtol=1e-4, atol=1e-5)


def test_a_growing_map_steps_without_recompiling() -> None:
    mapper, view, window = mapped("sparse", {"refine.interval": "10000"}, step="compiled")
    model = mapper.model
    with torch_threads(mapper.profile.threads):
        mapper.steps.step(view, window)
        model.anchors.reserve(2 * model.anchors.capacity, model.optimizer)  # compiled once more, the capacity a symbol
        mapper.steps.step(view, window)
        start, capacity = len(model.anchors), model.anchors.capacity
        grown = 0
        with torch.compiler.set_stance("fail_on_recompile"):
            for done in range(1, 51):
                mapper.steps.step(view, window)
                if done % 10 == 0:  # grow and prune
                    grown += mapper.steps._refine()
            model.anchors.reserve(2 * model.anchors.capacity, model.optimizer)
            mapper.steps.step(view, window)
    assert len(model.anchors) > start and grown > 0, "the map grew"
    assert model.anchors.capacity >= 2 * capacity, "its buffers doubled again"
