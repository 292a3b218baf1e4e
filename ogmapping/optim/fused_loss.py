"""The image terms of the mapping loss (colour L1, 1 - SSIM, depth L1) in one compiled CPU pass.

Through autograd these terms cost more than rendering: five grouped convolutions forward and
their transposes backward, plus some twenty full-image elementwise ops and their saved buffers.
Here one Numba pass computes the three values and their gradients with respect to the rendered
colour and depth together (the loss is a leaf of the graph, so the gradient is known as soon as
the values are); autograd's backward only scales the stored gradients.

SSIM gradient: with mu = G*x, e_xx = G*(x^2), e_xy = G*(x y) (G the zero-padded Gaussian window,
symmetric, so its adjoint is itself), dS/dx = G*(dS/dmu) + 2x G*(dS/de_xx) + y G*(dS/de_xy).
The rules are exactly those of ``ogmapping.optim.ssim`` and ``ogmapping.optim.losses`` (tests compare both).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ogmapping.arrays import float32_array, image_planes
from ogmapping.optim.blur import blur
from ogmapping.optim.ssim import C1, C2, TAPS, ReferenceStatistics, reference_statistics

_C1 = np.float32(C1)
_C2 = np.float32(C2)
_TWO = np.float32(2.0)


@njit(parallel=True, cache=True, error_model="numpy")
def _moments(x, y):
    """The planes SSIM blurs on the rendered side: x, x^2 and x y."""
    height, length = x.shape
    maps = np.empty((3, height, length), np.float32)
    for r in prange(height):
        for i in range(length):
            maps[0, r, i] = x[r, i]
            maps[1, r, i] = x[r, i] * x[r, i]
            maps[2, r, i] = x[r, i] * y[r, i]
    return maps


@njit(parallel=True, cache=True, error_model="numpy")
def _ssim_and_partials(blurred, mean_y, square_mean_y, scale):
    """Per-row SSIM sums and ``scale`` times dS/d(mu_x), dS/d(e_xx), dS/d(e_xy) per pixel.

    Written without dividing by the numerator factors, which can pass through zero.
    """
    _, height, length = blurred.shape
    sums = np.zeros(height, np.float64)
    partials = np.empty_like(blurred)
    for r in prange(height):
        total = 0.0
        for i in range(length):
            mx = blurred[0, r, i]
            my = mean_y[r, i]
            a1 = _TWO * mx * my + _C1
            a2 = _TWO * (blurred[2, r, i] - mx * my) + _C2
            b1 = mx * mx + my * my + _C1
            b2 = (blurred[1, r, i] - mx * mx) + (square_mean_y[r, i] - my * my) + _C2
            inverse = np.float32(1.0) / (b1 * b2)
            s = a1 * a2 * inverse
            total += s
            partials[0, r, i] = scale * (
                _TWO * my * (a2 - a1) * inverse - s * (_TWO * mx / b1 - _TWO * mx / b2)
            )
            partials[1, r, i] = scale * (-s / b2)
            partials[2, r, i] = scale * (_TWO * a1 * inverse)
        sums[r] = total
    return sums, partials


@njit(parallel=True, cache=True, error_model="numpy")
def _colour_terms(x, y, blurred_partials, l1_scale):
    """|x - y| row sums, d(mean |x - y|)/dx, and the SSIM gradient assembled from blurred partials."""
    height, length = x.shape
    sums = np.zeros(height, np.float64)
    grad_l1 = np.empty_like(x)
    grad_ssim = np.empty_like(x)
    for r in prange(height):
        total = 0.0
        for i in range(length):
            difference = x[r, i] - y[r, i]
            total += abs(difference)
            grad_l1[r, i] = l1_scale * np.sign(difference)
            grad_ssim[r, i] = (
                blurred_partials[0, r, i]
                + _TWO * x[r, i] * blurred_partials[1, r, i]
                + y[r, i] * blurred_partials[2, r, i]
            )
        sums[r] = total
    return sums, grad_l1, grad_ssim


@njit(parallel=True, cache=True, error_model="numpy")
def _depth_terms(depth, gt_depth):
    """Mean |depth - gt| over valid gt (positive, finite) and its gradient; 0 and 0 with none valid."""
    height, width = depth.shape
    sums = np.zeros(height, np.float64)
    counts = np.zeros(height, np.int64)
    for r in prange(height):
        for c in range(width):
            g = gt_depth[r, c]
            if g > 0 and np.isfinite(g):
                sums[r] += abs(depth[r, c] - g)
                counts[r] += 1
    valid = counts.sum()
    scale = np.float32(1.0 / valid) if valid > 0 else np.float32(0.0)
    grad = np.zeros_like(depth)
    for r in prange(height):
        for c in range(width):
            g = gt_depth[r, c]
            if g > 0 and np.isfinite(g):
                grad[r, c] = scale * np.sign(depth[r, c] - g)
    return (sums.sum() / valid if valid > 0 else 0.0), grad


class _ImageTerms(torch.autograd.Function):
    """(render colour, render depth) -> (colour L1, 1 - SSIM, depth L1), gradients precomputed."""

    @staticmethod
    def forward(ctx, color, depth, gt_color, gt_depth, reference):
        height, width, channels = color.shape
        x, y = image_planes(color), image_planes(gt_color)
        blurred = blur(_moments(x, y), TAPS, channels)
        count = x.size
        ssim_sums, partials = _ssim_and_partials(
            blurred, image_planes(reference.mean), image_planes(reference.square_mean), np.float32(-1.0 / count)
        )
        l1_sums, grad_l1, grad_ssim = _colour_terms(x, y, blur(partials, TAPS, channels), np.float32(1.0 / count))
        depth_l1, grad_depth = _depth_terms(float32_array(depth), float32_array(gt_depth))
        shape = (height, width, channels)
        like = {"dtype": color.dtype, "device": color.device}
        ctx.grads = (
            torch.from_numpy(grad_l1.reshape(shape)).to(**like),
            torch.from_numpy(grad_ssim.reshape(shape)).to(**like),
            torch.from_numpy(grad_depth).to(dtype=depth.dtype, device=depth.device),
        )
        return (
            color.new_tensor(l1_sums.sum() / count),
            color.new_tensor(1.0 - ssim_sums.sum() / count),
            depth.new_tensor(depth_l1),
        )

    @staticmethod
    def backward(ctx, grad_l1_out, grad_ssim_out, grad_depth_out):
        grad_l1, grad_ssim, grad_depth = ctx.grads
        grad_color = grad_l1 * grad_l1_out + grad_ssim * grad_ssim_out
        return grad_color, grad_depth * grad_depth_out, None, None, None


def image_terms(
    render_color: torch.Tensor,
    render_depth: torch.Tensor,
    gt_color: torch.Tensor,
    gt_depth: torch.Tensor,
    reference: ReferenceStatistics | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Colour L1, 1 - mean SSIM and valid-pixel depth L1 of one view, differentiable in the render.

    Shapes and rules as ``ogmapping.optim.losses.mapping_loss``; ``reference`` is
    ``reference_statistics(gt_color)`` when the caller has it cached.
    """
    reference = reference if reference is not None else reference_statistics(gt_color, compiled=True)
    return _ImageTerms.apply(render_color, render_depth, gt_color, gt_depth, reference)
