"""The Triton fused loss equals the autograd definitions, values and gradients (interpreted on the CPU)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_fused_loss import _reference_terms, _views
from triton_kernels import HAS_TRITON, NO_TRITON, triton_loss

import ogmapping.mapper
from ogmapping.config import LossConfig, resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.optim import fused_loss
from ogmapping.optim.losses import mapping_loss, window_mapping_loss
from ogmapping.optim.ssim import ReferenceStatistics, reference_statistics

pytestmark = pytest.mark.skipif(not HAS_TRITON, reason=NO_TRITON)
WEIGHTS = (0.8, 0.2, 0.5)


def _on(device: torch.device, *tensors: torch.Tensor) -> list[torch.Tensor]:
    return [t.detach().to(device).requires_grad_(t.requires_grad) for t in tensors]


def _weighted_backward(terms, inputs, weights=WEIGHTS) -> list[torch.Tensor]:
    total = sum(w * t for w, t in zip(weights, terms, strict=True))
    return list(torch.autograd.grad(total, inputs))


def _assert_close(mine, theirs) -> None:
    for m, t in zip(mine, theirs, strict=True):
        m, t = m.detach().cpu(), t.detach().cpu()
        scale = max(float(t.abs().max()), 1e-12)
        assert float((m - t).abs().max()) <= 1e-4 * scale, f"off by {float((m - t).abs().max()) / scale:.2e}"


def _check_view(height: int, width: int, seed: int, weights=WEIGHTS, gt_depth: torch.Tensor | None = None) -> None:
    module, device = triton_loss()
    color, depth, gt_color, measured = _views(height, width, seed)
    measured = measured if gt_depth is None else gt_depth
    reference = _reference_terms(color, depth, gt_color, measured)
    expected = _weighted_backward(reference, [color, depth], weights)
    color_d, depth_d, gt_color_d, measured_d = _on(device, color, depth, gt_color, measured)
    fused = module.window_terms(color_d[None], depth_d[None], gt_color_d[None], measured_d[None])[0].unbind()
    _assert_close(fused, reference)
    _assert_close(_weighted_backward(fused, [color_d, depth_d], weights), expected)


@pytest.mark.parametrize(("height", "width", "seed"), [(24, 17, 0), (40, 31, 1)])
def test_values_and_gradients_match_the_reference(height: int, width: int, seed: int) -> None:
    _check_view(height, width, seed)


def test_tiles_across_columns_join_without_a_seam() -> None:
    """Wider than a program's 64 columns: the window reaches across the tiles' border."""
    _check_view(9, 70, 2)


def test_a_single_row() -> None:
    _check_view(1, 9, 3)


def test_no_valid_depth_and_a_zero_weight() -> None:
    """No depth measured at all: the term is 0 and its gradient 0, not NaN; SSIM weighted 0 adds nothing."""
    _check_view(24, 17, 4, weights=(1.0, 0.0, 0.5), gt_depth=torch.zeros(24, 17))


def test_a_window_of_views_equals_each_view_alone() -> None:
    """Two views in one batch, with cached reference statistics, give each view's own terms and gradients."""
    module, device = triton_loss()
    views = [_views(24, 17, seed) for seed in (5, 6)]
    color, depth, gt_color, gt_depth = (torch.stack([v[i].detach() for v in views]).to(device) for i in range(4))
    color.requires_grad_()
    depth.requires_grad_()
    each = [reference_statistics(v[2], compiled=False) for v in views]
    cached = ReferenceStatistics(gt_color, torch.stack([s.mean for s in each]).to(device),
                                 torch.stack([s.square_mean for s in each]).to(device))
    terms = module.window_terms(color, depth, gt_color, gt_depth, cached)
    weights = torch.tensor([[0.8, 0.2, 0.5], [0.3, 0.9, 0.1]], device=device)
    grads = torch.autograd.grad((terms * weights).sum(), [color, depth])
    for index, (v_color, v_depth, v_gt_color, v_gt_depth) in enumerate(views):
        reference = _reference_terms(v_color, v_depth, v_gt_color, v_gt_depth)
        _assert_close(terms[index], torch.stack(reference))
        expected = _weighted_backward(reference, [v_color, v_depth], weights[index].tolist())
        _assert_close([grads[0][index], grads[1][index]], expected)


def test_the_window_loss_is_each_views_mapping_loss() -> None:
    _, device = triton_loss()
    views = [_views(12, 10, seed) for seed in (7, 8)]
    scales = [torch.rand(5, 3), torch.rand(4, 3)]
    drawn = [None, torch.tensor([True, False, True, True])]
    config = LossConfig()
    expected = [mapping_loss(*view, view_scales, config, compiled=False, drawn=view_drawn)[0]
                for view, view_scales, view_drawn in zip(views, scales, drawn, strict=True)]
    on_device = [_on(device, *view) for view in views]
    losses = window_mapping_loss(
        *([view[i] for view in on_device] for i in range(4)), [s.to(device) for s in scales], config,
        [reference_statistics(view[2], compiled=False) for view in on_device],
        [None if d is None else d.to(device) for d in drawn])
    assert losses.shape == (2,)
    _assert_close(losses, torch.stack(expected))
    inputs = [t for view in views for t in view[:2]]
    _assert_close(torch.autograd.grad(losses.sum(), [t for view in on_device for t in view[:2]]),
                  torch.autograd.grad(sum(expected), inputs))


def test_the_window_loss_corrects_each_view_by_its_exposure() -> None:
    """Stacked (a, b), one row per view, as each view's ``mapping_loss`` with its own: values and gradients."""
    _, device = triton_loss()
    views = [_views(12, 10, seed) for seed in (3, 4)]
    scales = [torch.rand(5, 3), torch.rand(4, 3)]
    config = LossConfig()
    exposures = torch.tensor([[0.0, 0.0], [-0.3, 0.05]], requires_grad=True)
    expected = [mapping_loss(*view, view_scales, config, compiled=False, exposure=view_exposure)[0]
                for view, view_scales, view_exposure in zip(views, scales, exposures.unbind(), strict=True)]
    on_device = [_on(device, *view) for view in views]
    stacked = _on(device, exposures)[0]
    losses = window_mapping_loss(
        *([view[i] for view in on_device] for i in range(4)), [s.to(device) for s in scales], config,
        [reference_statistics(view[2], compiled=False) for view in on_device], [None, None], stacked)
    _assert_close(losses, torch.stack(expected))
    _assert_close(torch.autograd.grad(losses.sum(), [stacked]), torch.autograd.grad(sum(expected), [exposures]))


@pytest.mark.parametrize("exposure", [False, True])
def test_a_mapping_step_with_the_profile_flag_takes_the_kernels_terms(monkeypatch, exposure: bool) -> None:
    """The step asks for the Triton terms once per image size of its window when the profile says so (the
    kernels stood in for by the CPU's fused terms here: the step's wiring is what is checked), with its
    views' exposures stacked where ``keyframes.exposure`` is on."""
    module, _ = triton_loss()
    calls = []

    def recorded(colors, depths, gt_colors, gt_depths, reference):
        calls.append(tuple(colors.shape))
        return torch.stack([torch.stack(fused_loss.image_terms(*view)) for view in zip(
            colors, depths, gt_colors, gt_depths, strict=True)])

    monkeypatch.setattr(module, "window_terms", recorded)
    chosen = ogmapping.mapper.execution_profile
    monkeypatch.setattr(ogmapping.mapper, "execution_profile",
                        lambda *args: dataclasses.replace(chosen(*args), triton_loss=True))
    source = SyntheticSource(n_frames=1, width=32, height=24)
    mapper = ogmapping.mapper.Mapper(resolve("sparse", overrides={"keyframes.first_iterations": 2,
                                                                  "keyframes.exposure": exposure}), "cpu")
    mapper.process(source[0])
    assert calls == [(1, 24, 32, 3)] * 2


def test_inputs_it_cannot_take_are_refused() -> None:
    module, device = triton_loss()
    color, depth, gt_color, gt_depth = (t[None] for t in _on(device, *_views(6, 5, 8)))
    with pytest.raises(ValueError, match="runs in float32"):
        module.window_terms(color.double(), depth, gt_color.double(), gt_depth)
    with pytest.raises(ValueError, match="depths matching the colours"):
        module.window_terms(color, depth[:, :, :4], gt_color, gt_depth)
    with pytest.raises(ValueError, match="colours of one shape"):
        module.window_terms(color, depth, gt_color[:, :, :4], gt_depth)
