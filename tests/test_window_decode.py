"""A window's Gaussians decoded in one pass of the decoders, or with static shapes, equal those decoded
view by view.

``generate_window(shared_decode=True)`` runs the decoders once over every (anchor, view) pair of a
step's window; ``static_gaussians.generate_drawn`` (the GPU's way) runs them over every row of the
anchor buffers in every view and marks the Gaussians drawn; view by view (the CPU's way) is the
definition. Views share anchors, as a window's do. Values and every gradient (decoders, anchor
tables) agree to float rounding, for the torch and the compiled assembly, with and without
per-anchor colours.
"""

from __future__ import annotations

import pytest
import torch

from ogmapping.model.decoders import Decoders
from ogmapping.model.gaussians import GaussianSet, generate_window
from ogmapping.model.static_gaussians import DrawnGaussianSet, generate_drawn
from ogmapping.structure.anchors import LEARNABLE, AnchorMap

N_OFFSETS, FEATURES, HIDDEN, COUNT, CAPACITY = 10, 8, 16, 120, 150
OUTPUTS = ("means", "quats", "scales", "opacities", "colors")


def window(with_colours: bool, shared_decode: bool, compiled: bool, static: bool = False):
    """Each view's Gaussians (static: only the drawn ones) and the gradients of a loss that weighs each
    (anchor, slot, value) the same whichever way it was decoded."""
    generator = torch.Generator().manual_seed(0)
    anchors = AnchorMap(N_OFFSETS, FEATURES, True, torch.device("cpu"), with_colours=with_colours, capacity=CAPACITY)
    anchors.add(torch.arange(COUNT), torch.zeros(COUNT, dtype=torch.int64), torch.randn(COUNT, 3, generator=generator),
                torch.rand(COUNT, generator=generator) * 0.1 + 0.01, torch.randn(COUNT, FEATURES, generator=generator),
                None, torch.randn(COUNT, 3, generator=generator) if with_colours else None)
    with torch.no_grad():
        anchors.offsets.normal_(generator=generator)
    decoders = Decoders(FEATURES, N_OFFSETS, HIDDEN, generator)
    rows = [torch.randperm(COUNT, generator=generator)[:size].sort().values for size in (90, 70, 0, 100)]
    centers = [torch.randn(3, generator=generator) * 2 for _ in rows]
    if static:
        masks = [torch.zeros(CAPACITY, dtype=torch.bool).index_fill_(0, view_rows, True) for view_rows in rows]
        drawn = generate_drawn(anchors, anchors.parameter("features"), decoders, torch.stack(centers),
                               torch.stack(masks))
        views = [drawn_only(view) for view in drawn.views()]
    else:
        views = generate_window(anchors, lambda r: anchors.parameter("features").index_select(0, r), decoders,
                                centers, rows, compiled=compiled, shared_decode=shared_decode)
    widths = dict(zip(OUTPUTS, (3, 4, 3, 1, 3), strict=True))
    weights = {name: torch.randn(len(rows), CAPACITY, N_OFFSETS, width, generator=generator)
               for name, width in widths.items()}
    loss = sum((getattr(view, name).reshape(len(view), widths[name])
                * weights[name][index, view.rows, view.slots]).sum()
               for index, view in enumerate(views) for name in OUTPUTS)
    loss.backward()
    named = [*((name, anchors.parameter(name)) for name in LEARNABLE), *decoders.named_parameters()]
    grads = {name: param.grad for name, param in named if param.grad is not None}
    return views, grads


@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("with_colours", [False, True])
def test_one_pass_of_the_decoders_equals_one_per_view(compiled: bool, with_colours: bool) -> None:
    per_view, per_view_grads = window(with_colours, shared_decode=False, compiled=compiled)
    shared, shared_grads = window(with_colours, shared_decode=True, compiled=compiled)
    assert len(shared) == len(per_view) == 4 and len(shared[2]) == 0
    for expected, actual in zip(per_view, shared, strict=True):
        for name in ("rows", "slots", "anchor_rows"):
            assert torch.equal(getattr(actual, name), getattr(expected, name)), name
        for name in (*OUTPUTS, "anchor_opacity"):
            torch.testing.assert_close(getattr(actual, name), getattr(expected, name), rtol=1e-5, atol=1e-6)
    assert shared_grads.keys() == per_view_grads.keys() and "offsets" in shared_grads
    assert ("colours" in shared_grads) == with_colours
    for name, grad in per_view_grads.items():
        torch.testing.assert_close(shared_grads[name], grad, rtol=1e-4, atol=1e-5, msg=name)


def drawn_only(view: DrawnGaussianSet) -> GaussianSet:
    """The drawn Gaussians of a view decoded with static shapes, as the dynamic decode lists them."""
    keep = view.drawn
    return GaussianSet(means=view.means[keep], quats=view.quats[keep], scales=view.scales[keep],
                       opacities=view.opacities[keep], colors=view.colors[keep], rows=view.rows[keep],
                       slots=view.slots[keep], anchor_rows=view.anchor_rows[view.in_view],
                       anchor_opacity=view.anchor_opacity[view.in_view])


@pytest.mark.parametrize("with_colours", [False, True])
def test_static_shapes_draw_what_the_dynamic_decode_selects(with_colours: bool) -> None:
    per_view, per_view_grads = window(with_colours, shared_decode=False, compiled=False)
    static, static_grads = window(with_colours, shared_decode=True, compiled=False, static=True)
    assert len(static) == 4 and len(static[2]) == 0 and len(static[0]) > 0
    for expected, actual in zip(per_view, static, strict=True):
        for name in ("rows", "slots", "anchor_rows"):
            assert torch.equal(getattr(actual, name), getattr(expected, name)), name
        for name in (*OUTPUTS, "anchor_opacity"):
            torch.testing.assert_close(getattr(actual, name), getattr(expected, name), rtol=1e-5, atol=1e-6)
    assert static_grads.keys() == per_view_grads.keys()
    for name, grad in per_view_grads.items():
        # the buffers' rows past the count get no gradient
        actual = static_grads[name][:COUNT] if grad.shape[0] == CAPACITY else static_grads[name]
        torch.testing.assert_close(actual, grad[:COUNT] if grad.shape[0] == CAPACITY else grad, rtol=1e-4,
                                   atol=1e-5, msg=name)
        if grad.shape[0] == CAPACITY:
            assert not static_grads[name][COUNT:].any(), name
