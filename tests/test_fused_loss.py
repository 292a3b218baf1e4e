"""The compiled image terms equal the autograd definitions, values and gradients."""

from __future__ import annotations

import pytest
import torch

from ogmapping.optim.fused_loss import image_terms
from ogmapping.optim.losses import depth_l1
from ogmapping.optim.ssim import reference_statistics, ssim_map


def _views(height: int, width: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    gt_color = torch.rand(height, width, 3, generator=g)
    color = (0.7 * gt_color + 0.3 * torch.rand(height, width, 3, generator=g)).requires_grad_()
    gt_depth = 0.5 + 3.0 * torch.rand(height, width, generator=g)
    gt_depth[: height // 4] = 0.0  # no measurement
    gt_depth[-1, 0] = float("nan")
    gt_depth[-1, 1] = float("inf")
    depth = (gt_depth.nan_to_num(0.0, 0.0) + 0.2 * torch.randn(height, width, generator=g)).requires_grad_()
    return color, depth, gt_color, gt_depth


def _reference_terms(color, depth, gt_color, gt_depth):
    return (
        (color - gt_color).abs().mean(),
        1.0 - ssim_map(color, gt_color, compiled=False).mean(),
        depth_l1(depth, gt_depth),
    )


@pytest.mark.parametrize(("height", "width", "seed"), [(24, 32, 0), (13, 40, 1), (120, 160, 2), (5, 7, 3)])
def test_values_and_gradients_match_the_autograd_definitions(height: int, width: int, seed: int) -> None:
    color, depth, gt_color, gt_depth = _views(height, width, seed)
    weights = torch.tensor([0.8, 0.2, 0.5])
    fused = image_terms(color, depth, gt_color, gt_depth, reference_statistics(gt_color, compiled=True))
    sum(w * t for w, t in zip(weights, fused, strict=True)).backward()
    fused_grads = color.grad.clone(), depth.grad.clone()
    color.grad, depth.grad = None, None
    reference = _reference_terms(color, depth, gt_color, gt_depth)
    sum(w * t for w, t in zip(weights, reference, strict=True)).backward()
    for mine, theirs in zip(fused, reference, strict=True):
        assert float(mine.detach()) == pytest.approx(float(theirs.detach()), rel=1e-5, abs=1e-7)
    for mine, theirs in zip(fused_grads, (color.grad, depth.grad), strict=True):
        scale = float(theirs.abs().max())
        assert float((mine - theirs).abs().max()) <= 1e-4 * scale


def test_each_output_carries_only_its_own_gradient() -> None:
    color, depth, gt_color, gt_depth = _views(16, 16, 4)
    l1, ssim, depth_term = image_terms(color, depth, gt_color, gt_depth)
    depth_term.backward(retain_graph=True)
    assert color.grad is None or float(color.grad.abs().sum()) == 0.0
    assert float(depth.grad.abs().sum()) > 0
    depth.grad = None
    (l1 + ssim).backward()
    assert float(color.grad.abs().sum()) > 0
    assert depth.grad is None or float(depth.grad.abs().sum()) == 0.0


def test_no_valid_depth_gives_zero_and_no_nan() -> None:
    color, depth, gt_color, _ = _views(16, 16, 5)
    _, _, depth_term = image_terms(color, depth, gt_color, torch.zeros(16, 16))
    depth_term.backward()
    assert float(depth_term.detach()) == 0.0 and not bool(torch.isnan(depth.grad).any())


def test_identical_images_give_zero_loss() -> None:
    _, _, gt_color, gt_depth = _views(20, 20, 6)
    clean_depth = gt_depth.nan_to_num(0.0, 0.0, 0.0)
    l1, ssim, depth_term = image_terms(gt_color.clone(), clean_depth, gt_color, clean_depth)
    assert float(l1) == 0.0 and float(depth_term) == 0.0
    assert float(ssim) == pytest.approx(0.0, abs=1e-6)


def test_float64_inputs_keep_their_dtype() -> None:
    color, depth, gt_color, gt_depth = _views(12, 12, 7)
    color64 = color.detach().double().requires_grad_()
    terms = image_terms(color64, depth.detach().double(), gt_color.double(), gt_depth.double())
    terms[1].backward()
    assert all(t.dtype == torch.float64 for t in terms) and color64.grad.dtype == torch.float64
