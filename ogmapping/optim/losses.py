"""The mapping loss of the paper: colour L1, (1 - SSIM), depth L1 on valid pixels, volume regulariser.

Each term is returned on its own as well, so the mapper can log them and tests can check that
every term reacts to its own input only. In a compiled execution profile (the CPU with the ``cpu``
backend, ``ogmapping.runtime.profile``) the three image terms come from one compiled pass
(``ogmapping.optim.fused_loss``); otherwise from the autograd definitions below. On CUDA with triton,
``window_mapping_loss`` takes them for every view of one size from two Triton kernels
(``ogmapping.optim.triton_loss``) in one batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ogmapping.config import LossConfig
from ogmapping.optim.exposure import exposed
from ogmapping.optim.fused_loss import image_terms
from ogmapping.optim.ssim import ReferenceStatistics, ssim_map
from ogmapping.render.views import grouped


def depth_l1(render_depth: torch.Tensor, gt_depth: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean |rendered - measured| over pixels with a valid (positive, finite) measurement, and within
    ``mask`` (bool) where given; 0 if none.

    A masked sum over whole images rather than a gather of the valid pixels: the gather's size
    depends on the data, which on CUDA makes the host wait for the device at every view.
    """
    measured = torch.nan_to_num(gt_depth, nan=0.0, posinf=0.0, neginf=0.0)  # invalid -> 0, never NaN * 0
    valid = measured > 0 if mask is None else (measured > 0) & mask
    total = torch.where(valid, (render_depth - measured).abs(), 0.0).sum()
    return total / valid.sum().clamp_min(1)


def mean_volume(scales: torch.Tensor, drawn: torch.Tensor | None = None) -> torch.Tensor:
    """Mean product of the scales (the volume regulariser) over the Gaussians drawn; 0 if none."""
    if drawn is not None:  # the product written out: in a graph it fuses, where prod's backward does not
        volume = scales[:, 0] * scales[:, 1] * scales[:, 2]
        return torch.where(drawn, volume, 0.0).sum() / drawn.sum().clamp_min(1)
    return scales.prod(dim=-1).mean() if scales.numel() else scales.sum() * 0.0


def mapping_loss(
    render_color: torch.Tensor,
    render_depth: torch.Tensor,
    gt_color: torch.Tensor,
    gt_depth: torch.Tensor,
    scales: torch.Tensor,
    weights: LossConfig,
    gt_statistics: ReferenceStatistics | None = None,
    *,
    compiled: bool,
    drawn: torch.Tensor | None = None,
    exposure: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Weighted sum of the four terms for one view.

    ``render_color``/``gt_color`` (H, W, 3) in [0, 1], depths (H, W) in metres (gt 0 = no
    measurement), ``scales`` (N, 3) of the Gaussians that were rendered; ``gt_statistics`` is the
    cached SSIM side of ``gt_color`` when the caller has it. ``compiled`` takes the image terms from
    ``fused_loss`` (CPU tensors) instead of autograd; both give the same values and gradients.
    ``drawn`` (N,) marks the Gaussians drawn where ``scales`` holds inert ones too (static shapes).
    ``exposure`` (2,), the view's (a, b) (``ogmapping.optim.exposure``), corrects the render's colour
    before the colour and SSIM terms.
    """
    if exposure is not None:
        render_color = exposed(render_color, exposure)
    if compiled:
        color, ssim, depth = image_terms(render_color, render_depth, gt_color, gt_depth, gt_statistics)
    else:
        color = (render_color - gt_color).abs().mean()
        ssim = 1.0 - ssim_map(render_color, gt_color, gt_statistics, compiled=False).mean()
        depth = depth_l1(render_depth, gt_depth)
    parts = {
        "color": color,
        "ssim": ssim,
        "depth": depth,
        "scale": mean_volume(scales, drawn),
    }
    total = (
        weights.color * parts["color"]
        + weights.ssim * parts["ssim"]
        + weights.depth * parts["depth"]
        + weights.scale * parts["scale"]
    )
    return total, parts


def window_mapping_loss(
    render_colors: list[torch.Tensor],
    render_depths: list[torch.Tensor],
    gt_colors: list[torch.Tensor],
    gt_depths: list[torch.Tensor],
    scales: list[torch.Tensor],
    weights: LossConfig,
    gt_statistics: list[ReferenceStatistics],
    drawn: list[torch.Tensor | None],
    exposures: torch.Tensor | None = None,
) -> torch.Tensor:
    """``mapping_loss`` of each of a window's views of one image size, (B,): the image terms from the
    Triton kernels, all views in one batch (float32 CUDA tensors, or CPU ones when interpreted);
    ``exposures`` (B, 2), each view's (a, b), as ``mapping_loss``'s ``exposure``."""
    from ogmapping.optim.triton_loss import window_terms

    cached = ReferenceStatistics(*(torch.stack([getattr(statistics, name) for statistics in gt_statistics])
                                   for name in ("image", "mean", "square_mean")))
    colors = torch.stack(render_colors)
    if exposures is not None:
        colors = exposed(colors, exposures)
    terms = window_terms(colors, torch.stack(render_depths), torch.stack(gt_colors), torch.stack(gt_depths), cached)
    volume = torch.stack([mean_volume(view_scales, view_drawn) for view_scales, view_drawn in zip(
        scales, drawn, strict=True)])
    image = weights.color * terms[:, 0] + weights.ssim * terms[:, 1] + weights.depth * terms[:, 2]
    return image + weights.scale * volume


def same_size_groups(images: list[torch.Tensor]) -> list[list[int]]:
    """The positions of ``images`` grouped by shape, each group in order, the groups by first appearance."""
    return grouped(tuple(image.shape) for image in images)


def tracking_loss(
    render_color: torch.Tensor,
    render_depth: torch.Tensor,
    render_alpha: torch.Tensor,
    gt_color: torch.Tensor,
    gt_depth: torch.Tensor,
    weights: LossConfig,
    min_alpha: float,
) -> torch.Tensor:
    """Colour and depth L1 for a pose against a fixed map, over the pixels the map covers (rendered
    alpha at least ``min_alpha``, as SplaTAM tracks): where the map has nothing yet (newly seen space,
    always at the side the camera turns to) the loss would pull every pose the same way."""
    covered = render_alpha.detach() >= min_alpha
    color = torch.where(covered.unsqueeze(-1), (render_color - gt_color).abs(), 0.0).sum()
    color = color / (3 * covered.sum()).clamp_min(1)
    return weights.color * color + weights.depth * depth_l1(render_depth, gt_depth, covered)


@dataclass(frozen=True)
class TrackingMask:
    """The pixels a tracking residual counts: those the map covers (colour), and of them those with a
    valid depth (depth). Gauss-Newton tracking holds one fixed across the renders of a step."""

    covered: torch.Tensor  # (H, W) bool
    depth_valid: torch.Tensor  # (H, W) bool


def tracking_mask(render_alpha: torch.Tensor, gt_depth: torch.Tensor, min_alpha: float) -> TrackingMask:
    """``tracking_loss``'s pixels for a render whose alpha is ``render_alpha``."""
    covered = render_alpha.detach().reshape(gt_depth.shape) >= min_alpha
    measured = torch.nan_to_num(gt_depth, nan=0.0, posinf=0.0, neginf=0.0)
    return TrackingMask(covered, covered & (measured > 0))


def tracking_residuals(
    render_color: torch.Tensor,
    render_depth: torch.Tensor,
    gt_color: torch.Tensor,
    gt_depth: torch.Tensor,
    weights: LossConfig,
    mask: TrackingMask,
) -> torch.Tensor:
    """``tracking_loss`` as a vector whose absolute values sum to it (over ``mask``'s pixels): the
    weighted colour residuals of every pixel, then the depth residuals; 0 outside the mask."""
    colour = torch.where(mask.covered.unsqueeze(-1), render_color - gt_color, 0.0)
    colour = colour.reshape(-1) * (weights.color / (3 * mask.covered.sum()).clamp_min(1))
    measured = torch.nan_to_num(gt_depth, nan=0.0, posinf=0.0, neginf=0.0)
    depth = torch.where(mask.depth_valid, render_depth.reshape(gt_depth.shape) - measured, 0.0)
    depth = depth.reshape(-1) * (weights.depth / mask.depth_valid.sum().clamp_min(1))
    return torch.cat([colour, depth])
