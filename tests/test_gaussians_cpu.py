"""The Numba Gaussian assembly equals the torch one: outputs and gradients, on random anchors."""

import pytest
import torch

from ogmapping.model.gaussians import _assemble_compiled, _assemble_torch
from ogmapping.structure.anchors import AnchorMap

N_OFFSETS = 10
OUTPUTS = ("means", "quats", "scales", "opacities", "colors")


def _anchors(count: int, seed: int) -> AnchorMap:
    generator = torch.Generator().manual_seed(seed)
    anchors = AnchorMap(N_OFFSETS, 8, True, torch.device("cpu"))
    codes = torch.arange(count)
    sizes = torch.rand(count, generator=generator) * 0.1 + 0.01
    anchors.add(codes, torch.zeros(count, dtype=torch.int64), torch.randn(count, 3, generator=generator),
                sizes, torch.randn(count, 8, generator=generator), None)
    with torch.no_grad():
        anchors.offsets.normal_(generator=generator)
        anchors.log_scales.add_(torch.randn(count, 3, generator=generator) * 0.3)
    return anchors


def _logits(count: int, seed: int, opacity_shift: float) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(seed + 1)
    shapes = ((count, N_OFFSETS), (count, 3 * N_OFFSETS), (count, 7 * N_OFFSETS))
    logits = [torch.randn(shape, generator=generator) * 2 for shape in shapes]
    logits[0] += opacity_shift
    if count:
        logits[0][0, :3] = 0.0  # tanh(0) = 0: not kept, on both paths
    return [t.requires_grad_() for t in logits]


def _run(assemble, anchors: AnchorMap, rows: torch.Tensor, logits: list[torch.Tensor], seed: int):
    learnable = (anchors.parameter("log_scales"), anchors.parameter("offsets"))
    for param in (*learnable, *logits):
        param.grad = None
    gaussians = assemble(anchors, rows, *logits)
    generator = torch.Generator().manual_seed(seed + 2)
    loss = sum((getattr(gaussians, name) * torch.randn(getattr(gaussians, name).shape, generator=generator)).sum()
               for name in OUTPUTS)
    if len(gaussians):
        loss.backward()
    grads = [p.grad if p.grad is not None else torch.zeros_like(p)
             for p in (*learnable, *logits)]
    return gaussians, grads


@pytest.mark.parametrize(("count", "in_view", "opacity_shift", "seed"),
                         [(200, 150, -1.0, 0), (60, 60, 2.0, 1), (40, 0, 0.0, 2), (30, 20, -50.0, 3)])
def test_fused_assembly_matches_torch(count, in_view, opacity_shift, seed):
    anchors = _anchors(count, seed)
    rows = torch.randperm(count, generator=torch.Generator().manual_seed(seed))[:in_view]
    logits = _logits(in_view, seed, opacity_shift)
    def assemble_torch(anchors, rows, *logits):
        return _assemble_torch(anchors, rows, anchors.positions[rows], *logits)

    expected, expected_grads = _run(assemble_torch, anchors, rows, logits, seed)
    actual, actual_grads = _run(_assemble_compiled, anchors, rows, logits, seed)
    assert len(actual) == len(expected)
    for name in OUTPUTS:
        torch.testing.assert_close(getattr(actual, name), getattr(expected, name), rtol=1e-5, atol=1e-6)
    for name in ("rows", "slots", "anchor_rows"):
        assert torch.equal(getattr(actual, name), getattr(expected, name)), name
    torch.testing.assert_close(actual.anchor_opacity, expected.anchor_opacity, rtol=1e-5, atol=1e-6)
    for got, want in zip(actual_grads, expected_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
