"""A window's Gaussians decoded in one pass of the decoders equal those decoded view by view.

``generate_window(shared_decode=True)`` (the GPU's way) runs the decoders once over every
(anchor, view) pair of a step's window; view by view (the CPU's way) is the definition. Views
share anchors, as a window's do. Values and every gradient (decoders, anchor tables) agree to
float rounding, for the torch and the compiled assembly, with and without per-anchor colours.
"""

from __future__ import annotations

import pytest
import torch

from ogmapping.model.decoders import Decoders
from ogmapping.model.gaussians import generate_window
from ogmapping.structure.anchors import AnchorMap

N_OFFSETS, FEATURES, HIDDEN, COUNT = 10, 8, 16, 120
OUTPUTS = ("means", "quats", "scales", "opacities", "colors")


def window(with_colours: bool, shared_decode: bool, compiled: bool):
    generator = torch.Generator().manual_seed(0)
    anchors = AnchorMap(N_OFFSETS, FEATURES, True, torch.device("cpu"), with_colours=with_colours)
    anchors.add(torch.arange(COUNT), torch.zeros(COUNT, dtype=torch.int64), torch.randn(COUNT, 3, generator=generator),
                torch.rand(COUNT, generator=generator) * 0.1 + 0.01, torch.randn(COUNT, FEATURES, generator=generator),
                None, torch.randn(COUNT, 3, generator=generator) if with_colours else None)
    with torch.no_grad():
        anchors.offsets.normal_(generator=generator)
    decoders = Decoders(FEATURES, N_OFFSETS, HIDDEN, generator)
    rows = [torch.randperm(COUNT, generator=generator)[:size].sort().values for size in (90, 70, 0, 100)]
    centers = [torch.randn(3, generator=generator) * 2 for _ in rows]
    views = generate_window(anchors, lambda r: anchors.features.index_select(0, r), decoders, centers, rows,
                            compiled=compiled, shared_decode=shared_decode)
    loss = sum((getattr(view, name) * torch.randn(getattr(view, name).shape, generator=generator)).sum()
               for view in views for name in OUTPUTS)
    loss.backward()
    grads = {name: param.grad for name, param in [*anchors.named_parameters(), *decoders.named_parameters()]
             if param.grad is not None}
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
