"""The compiled Triton fused loss on a GPU, at full size: against the reference, in a compiled graph, and timed.

The reference is the autograd definition in float64 (so neither side's rounding, nor cuDNN's TF32
convolutions, decide the comparison); the kernels run in float32 and match it within 1e-4 relative.
The timing (one view's mapping loss forward and backward, CUDA events, median of 20) goes to the terminal and
to ``$OGMAP_GPU_REPORT/triton-loss.json`` (``bench/gpu/check.sh`` sets it); the kernels must beat
the float32 reference.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch
from test_fused_loss import _reference_terms
from triton_kernels import HAS_TRITON, NO_TRITON, interpreted, median_ms

from ogmapping.config import LossConfig
from ogmapping.optim.losses import mapping_loss, window_mapping_loss
from ogmapping.optim.ssim import reference_statistics

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
              pytest.mark.skipif(not HAS_TRITON, reason=NO_TRITON)]
SIZES = [(480, 640), (680, 1200)]
WEIGHTS = (0.8, 0.2, 0.5)


def _kernels():
    from ogmapping.optim import triton_loss

    if interpreted(triton_loss):
        pytest.skip("TRITON_INTERPRET=1 is set in this pytest process: run the GPU tests on their own (pytest -m gpu)")
    return triton_loss


def _views(count: int, height: int, width: int, seed: int) -> list[torch.Tensor]:
    g = torch.Generator(device="cuda").manual_seed(seed)
    gt_color = torch.rand(count, height, width, 3, device="cuda", generator=g)
    color = 0.7 * gt_color + 0.3 * torch.rand(count, height, width, 3, device="cuda", generator=g)
    gt_depth = 0.5 + 3.0 * torch.rand(count, height, width, device="cuda", generator=g)
    gt_depth[:, : height // 4] = 0.0
    gt_depth[:, -1, 0] = float("nan")
    depth = gt_depth.nan_to_num(0.0) + 0.2 * torch.randn(count, height, width, device="cuda", generator=g)
    return [color, depth, gt_color, gt_depth]


def _reference(color, depth, gt_color, gt_depth, weights=WEIGHTS):
    """Terms and weighted gradients of one view in float64 autograd."""
    color, depth = (t.double().requires_grad_() for t in (color, depth))
    terms = _reference_terms(color, depth, gt_color.double(), gt_depth.double())
    grads = torch.autograd.grad(sum(w * t for w, t in zip(weights, terms, strict=True)), [color, depth])
    return torch.stack(terms).detach(), grads


def _close(mine: torch.Tensor, theirs: torch.Tensor, what: str) -> None:
    error = float((mine.double() - theirs).abs().max()) / max(float(theirs.abs().max()), 1e-12)
    assert error <= 1e-4, f"{what}: off by {error:.2e} of its largest value"


@pytest.mark.parametrize(("height", "width"), SIZES)
def test_a_window_matches_the_reference_at_full_size(height: int, width: int) -> None:
    kernels = _kernels()
    color, depth, gt_color, gt_depth = _views(3, height, width, seed=height)
    color.requires_grad_()
    depth.requires_grad_()
    terms = kernels.window_terms(color, depth, gt_color, gt_depth)
    weights = torch.tensor([WEIGHTS, (0.3, 0.9, 0.1), (1.0, 0.0, 0.0)], device="cuda")
    grad_color, grad_depth = torch.autograd.grad((terms * weights).sum(), [color, depth])
    for view in range(3):
        expected, (expected_color, expected_depth) = _reference(
            color[view].detach(), depth[view].detach(), gt_color[view], gt_depth[view], weights[view].tolist())
        _close(terms[view].detach(), expected, f"terms of view {view}")
        _close(grad_color[view], expected_color, f"colour gradient of view {view}")
        _close(grad_depth[view], expected_depth, f"depth gradient of view {view}")


def test_the_compiled_step_graph_traces_the_kernels() -> None:
    """``window_mapping_loss`` compiled whole (as ``ogmapping.mapping.graphs`` compiles it) equals it eager."""
    _kernels()
    views = _views(2, 480, 640, seed=1)
    scales = [torch.rand(100, 3, device="cuda"), torch.rand(80, 3, device="cuda")]
    statistics_y = [reference_statistics(image, compiled=False) for image in views[2]]
    results = []
    for run in (window_mapping_loss, torch.compile(window_mapping_loss, fullgraph=True)):
        colors, depths = ([image.clone().requires_grad_() for image in batch] for batch in views[:2])
        losses = run(colors, depths, list(views[2]), list(views[3]), scales, LossConfig(), statistics_y, [None, None])
        results.append((losses.detach(), *torch.autograd.grad(losses.sum(), [*colors, *depths])))
    for eager, compiled in zip(*results, strict=True):
        _close(compiled, eager.double(), "compiled against eager")


def _timings(color, depth, gt_color, gt_depth) -> dict[str, float]:
    """One view's mapping loss, forward and backward, through the kernels and through the reference."""
    statistics_y = reference_statistics(gt_color, compiled=False)
    x, d, no_scales = color.requires_grad_(), depth.requires_grad_(), torch.zeros(0, 3, device="cuda")

    def fused():
        losses = window_mapping_loss([x], [d], [gt_color], [gt_depth], [no_scales], LossConfig(), [statistics_y],
                                     [None])
        torch.autograd.grad(losses.sum(), [x, d])

    def reference():
        total, _ = mapping_loss(x, d, gt_color, gt_depth, no_scales, LossConfig(), statistics_y, compiled=False)
        torch.autograd.grad(total, [x, d])

    return {"triton_ms": median_ms(fused), "reference_ms": median_ms(reference)}


def test_the_kernels_beat_the_reference() -> None:
    _kernels()
    report = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__}
    for height, width in SIZES:
        figures = _timings(*(t[0] for t in _views(1, height, width, seed=2)))
        report[f"{width}x{height}"] = figures
        print(f"\nloss forward+backward at {width}x{height} on {report['gpu']}: Triton {figures['triton_ms']:.3f} ms, "
              f"torch reference {figures['reference_ms']:.3f} ms")
        assert figures["triton_ms"] < figures["reference_ms"]
    folder = os.environ.get("OGMAP_GPU_REPORT")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / "triton-loss.json").write_text(json.dumps(report, indent=2) + "\n")
