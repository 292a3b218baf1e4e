"""The render and optimiser options in a mapping step: which screen-space gradient growth reads
(``render.absgrad``), which anchor rows Adam steps (``optim.selective``), and which backends take them."""

from __future__ import annotations

import pytest
import torch
from steady_step import mapped

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.mapping import steps as steps_module
from ogmapping.mapping.steps import seen_rows
from ogmapping.optim import refine


def test_gsplat_only_options_are_refused_on_other_backends_and_packed_is_not():
    for key in ("render.absgrad", "render.antialiased"):
        with pytest.raises(ValueError, match=rf"{key}: gsplat's options only .* the cpu backend"):
            Mapper(resolve("sparse", overrides={key: "true"}), "cpu")
    mapper = Mapper(resolve("sparse", overrides={"render.packed": "true", "optim.selective": "true"}), "cpu")
    assert mapper.model.raster_options.packed


@pytest.fixture(scope="module")
def selective_map():
    """A mapper with ``optim.selective`` a few frames into the synthetic room, and its next view and window."""
    return mapped("sparse", {"refine.interval": "10000", "optim.selective": "true"})


def test_growth_reads_the_absolute_gradient_only_with_absgrad(monkeypatch, selective_map):
    """A stand-in backend gives every render an absolute gradient of 7s; the statistics get it only where
    ``render.absgrad`` is set, else the gradient of ``means2d``."""
    mapper, view, window = selective_map
    rasterize_batch = steps_module.rasterize_batch

    def with_absgrad(*args, **kwargs):
        outputs = rasterize_batch(*args, **kwargs)
        for output in outputs:
            output.absgrad = lambda output=output: torch.full_like(output.means2d, 7.0)
        return outputs

    received = []
    accumulate = refine.accumulate
    monkeypatch.setattr(steps_module, "rasterize_batch", with_absgrad)
    monkeypatch.setattr(refine, "accumulate", lambda anchors, gaussians, grad, *rest: (
        received.append(grad), accumulate(anchors, gaussians, grad, *rest)))
    for absgrad in (False, True):
        mapper.config.render.absgrad = absgrad
        mapper.steps.step(view, window)
        assert len(received) == 3
        for grad in received:
            assert bool((grad == 7.0).all()) == absgrad
        received.clear()
    mapper.config.render.absgrad = False


def step_with_far_rows(mapper, view, window) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """One step after every other live anchor is moved a kilometre away (out of every view): each
    selective row parameter's value and first moment before the step, and the rows seen and not seen."""
    model = mapper.model
    with torch.no_grad():
        model.anchors.buffer("positions")[1: len(model.anchors): 2] += 1000.0
    rows = {name: model.anchors.parameter(name) for name in ("log_scales", "offsets", "features")}
    before = {name: (param.detach().clone(), model.optimizer.state[param]["exp_avg"].clone())
              for name, param in rows.items()}
    rendered = []
    objective = mapper.steps.objective

    def kept(*args):
        result = objective(*args)
        rendered.extend(result[1])
        return result

    mapper.steps.objective = kept
    mapper.steps.step(view, window)
    del mapper.steps.objective
    seen = seen_rows(model.anchors.capacity, rendered)
    return before, seen, model.anchors.live & ~seen


@pytest.mark.parametrize("step", ["dynamic", "static"])
def test_selective_steps_leave_unseen_rows_and_their_moments_alone(step: str, selective_map):
    mapper, view, window = selective_map if step == "dynamic" else mapped(
        "sparse", {"refine.interval": "10000", "optim.selective": "true"}, step=step)
    before, seen, unseen = step_with_far_rows(mapper, view, window)
    assert seen.any() and unseen.any()
    for name, (value, moment) in before.items():
        param = mapper.model.anchors.parameter(name)
        assert moment[unseen].any(), name  # earlier steps moved them: plain Adam would again
        assert torch.equal(param.detach()[unseen], value[unseen]), name
        assert torch.equal(mapper.model.optimizer.state[param]["exp_avg"][unseen], moment[unseen]), name
        assert not torch.equal(param.detach()[seen], value[seen]), name
