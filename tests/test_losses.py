"""Each loss term responds to its own input, and gradients reach the rendered images."""

from __future__ import annotations

import pytest
import torch

from ogmapping.config import LossConfig
from ogmapping.optim.losses import mapping_loss, mean_volume, same_size_groups
from ogmapping.optim.ssim import _blur, gaussian_window


def _scene(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(16, 16, 3, generator=g)
    depth = 1.0 + torch.rand(16, 16, generator=g)
    scales = 0.05 + 0.1 * torch.rand(5, 3, generator=g)
    return color, depth, scales


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "autograd"])
def test_perfect_render_leaves_only_the_scale_term(compiled):
    color, depth, scales = _scene()
    total, parts = mapping_loss(color, depth, color, depth, scales, LossConfig(), compiled=compiled)
    assert parts["color"] == 0 and parts["depth"] == 0
    assert parts["ssim"] == pytest.approx(0.0, abs=1e-6)
    assert parts["scale"] == pytest.approx(float(scales.prod(-1).mean()))
    assert total == pytest.approx(LossConfig().scale * float(parts["scale"]), abs=1e-6)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "autograd"])
def test_terms_are_separate(compiled):
    color, depth, scales = _scene()
    wrong_depth = depth + 0.3
    _, parts = mapping_loss(color, wrong_depth, color, depth, scales, LossConfig(), compiled=compiled)
    assert parts["depth"] == pytest.approx(0.3, abs=1e-5) and parts["color"] == 0
    _, parts = mapping_loss(color * 0.5, depth, color, depth, scales, LossConfig(), compiled=compiled)
    assert parts["color"] > 0 and parts["ssim"] > 0 and parts["depth"] == 0


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "autograd"])
def test_depth_uses_valid_pixels_only(compiled):
    color, depth, scales = _scene()
    gt = depth.clone()
    gt[:8] = 0.0
    render = depth.clone()
    render[:8] = 9.0  # wrong only where there is no measurement
    _, parts = mapping_loss(color, render, color, gt, scales, LossConfig(), compiled=compiled)
    assert parts["depth"] == 0
    _, parts = mapping_loss(color, render, color, torch.zeros_like(gt), scales, LossConfig(), compiled=compiled)
    assert parts["depth"] == 0


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "autograd"])
def test_non_finite_measurements_are_invalid_and_pass_no_gradient(compiled):
    color, depth, scales = _scene()
    gt = depth.clone()
    gt[0], gt[1], gt[2], gt[3] = float("nan"), float("inf"), float("-inf"), -1.0
    render = (depth + 0.25 * torch.rand(16, 16, generator=torch.Generator().manual_seed(1))).requires_grad_()
    _, parts = mapping_loss(color, render, color, gt, scales, LossConfig(), compiled=compiled)
    valid = torch.isfinite(gt) & (gt > 0)
    expected = (render[valid] - gt[valid]).abs().mean()
    assert float(parts["depth"].detach()) == pytest.approx(float(expected.detach()), rel=1e-6)
    parts["depth"].backward()
    assert bool(torch.isfinite(render.grad).all()) and bool((render.grad[~valid] == 0).all())


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "autograd"])
def test_weights_and_gradients(compiled):
    color, depth, scales = _scene()
    render_color = (color * 0.8).requires_grad_()
    render_depth = (depth + 0.1).requires_grad_()
    scales = scales.clone().requires_grad_()
    weights = LossConfig(color=1.0, ssim=2.0, depth=3.0, scale=4.0)
    total, parts = mapping_loss(render_color, render_depth, color, depth, scales, weights, compiled=compiled)
    expected = parts["color"] + 2 * parts["ssim"] + 3 * parts["depth"] + 4 * parts["scale"]
    assert float(total.detach()) == pytest.approx(float(expected.detach()))
    total.backward()
    for tensor in (render_color, render_depth, scales):
        assert tensor.grad is not None and tensor.grad.abs().sum() > 0


def test_cached_reference_statistics_give_the_same_ssim():
    from ogmapping.optim.ssim import reference_statistics, ssim_map

    generator = torch.Generator().manual_seed(3)
    a, b = torch.rand(20, 24, 3, generator=generator), torch.rand(20, 24, 3, generator=generator)
    for compiled in (True, False):
        cached = ssim_map(a, b, reference_statistics(b, compiled=compiled), compiled=compiled)
        assert torch.allclose(cached, ssim_map(a, b, compiled=compiled), atol=1e-6)


def test_compiled_blur_gives_the_autograd_ssim():
    """The Numba blur and torch's differentiable one give the same map; the Numba one refuses a gradient."""
    from ogmapping.optim.ssim import reference_statistics, ssim_map

    generator = torch.Generator().manual_seed(4)
    a, b = torch.rand(37, 53, 3, generator=generator), torch.rand(37, 53, 3, generator=generator)
    differentiable = ssim_map(a.clone().requires_grad_(), b.clone().requires_grad_(), compiled=False)
    compiled = ssim_map(a, b, compiled=True)
    assert differentiable.requires_grad and not compiled.requires_grad
    torch.testing.assert_close(compiled, differentiable.detach(), rtol=1e-5, atol=1e-5)
    reference = reference_statistics(b, compiled=True)
    torch.testing.assert_close(ssim_map(a, b, reference, compiled=False), compiled, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="no gradient"):
        ssim_map(a.clone().requires_grad_(), b, compiled=True)


def test_the_blur_in_a_compiled_graph_equals_the_convolution():
    """Inside a compiled graph the SSIM blur is a sum of shifted images (it fuses there); the same values
    and gradients as the convolutions it replaces."""
    generator = torch.Generator().manual_seed(0)
    image = torch.rand(1, 3, 30, 41, generator=generator, requires_grad=True)
    weights = torch.rand(1, 3, 30, 41, generator=generator)
    taps = gaussian_window()
    results = []
    for blur in (_blur, torch.compile(_blur, fullgraph=True)):
        image.grad = None
        blurred = blur(image, taps)
        (blurred * weights).sum().backward()
        results.append((blurred.detach(), image.grad.clone()))
    (expected, expected_grad), (actual, actual_grad) = results
    torch.testing.assert_close(actual, expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(actual_grad, expected_grad, rtol=1e-5, atol=1e-6)


def test_the_volume_term_averages_the_drawn_gaussians_only():
    scales = torch.rand(6, 3, requires_grad=True)
    drawn = torch.tensor([True, False, True, True, False, False])
    mean_volume(scales, drawn).backward()
    subset = scales.detach()[drawn].clone().requires_grad_()
    mean_volume(subset).backward()
    torch.testing.assert_close(mean_volume(scales.detach(), drawn), mean_volume(subset.detach()))
    torch.testing.assert_close(scales.grad[drawn], subset.grad)
    assert not scales.grad[~drawn].any()
    assert float(mean_volume(scales.detach(), torch.zeros(6, dtype=torch.bool))) == 0.0


def test_views_are_grouped_by_image_size() -> None:
    images = [torch.zeros(4, 6, 3), torch.zeros(2, 3, 3), torch.zeros(4, 6, 3), torch.zeros(2, 3, 3)]
    assert same_size_groups(images) == [[0, 2], [1, 3]]
    assert same_size_groups([]) == []
