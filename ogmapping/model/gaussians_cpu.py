"""Numba assembly of a view's Gaussians from the decoders' raw outputs, with a hand-written backward.

``gaussians.assemble`` in torch is some twenty small ops forward (activations, the anchor gathers,
the positive-opacity filter and five gathers of the kept Gaussians) and as many backward (five
scatters, the chain rule of each activation); on a sparse map each pays dispatch and a pass over
memory for a few thousand Gaussians, and together they cost more than the decoders' matmuls. Here
one parallel loop over the anchors in view does an anchor's Gaussians in registers, and the
backward writes each anchor's gradients straight into the full parameter tables (rows in view are
distinct, so no two anchors write the same row).

The arithmetic follows the torch assembly operation by operation in float32; activations come from
numba's libm rather than torch's vectorised ones, so values agree to float32 rounding (the parity
tests check values and gradients against the torch assembly).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ogmapping.arrays import float32_array

_ONE = np.float32(1.0)


@njit(cache=True, error_model="numpy")
def _sigmoid(x):
    return _ONE / (_ONE + np.exp(-x))


@njit(cache=True, error_model="numpy")
def _kept_starts(opacity_logits):
    """First output index of each anchor's kept Gaussians (positive tanh <=> positive logit)."""
    count, n = opacity_logits.shape
    starts = np.empty(count + 1, np.int64)
    starts[0] = 0
    for a in range(count):
        kept = 0
        for s in range(n):
            kept += opacity_logits[a, s] > 0
        starts[a + 1] = starts[a] + kept
    return starts


@njit(cache=True, parallel=True, error_model="numpy")
def assemble_forward(opacity_logits, color_logits, cov, positions, log_scales, offsets, rows, starts):
    """Kept Gaussians' means, quats, scales, opacities, colours, anchor rows and slots; each
    anchor's largest opacity (kept or not); and the scale factors, for the backward."""
    count, n = opacity_logits.shape
    total = starts[count]
    means = np.empty((total, 3), np.float32)
    quats = np.empty((total, 4), np.float32)
    scales = np.empty((total, 3), np.float32)
    opacities = np.empty(total, np.float32)
    colors = np.empty((total, 3), np.float32)
    kept_rows = np.empty(total, np.int64)
    slots = np.empty(total, np.int64)
    factors = np.empty((total, 3), np.float32)
    anchor_opacity = np.empty(count, np.float32)
    for a in prange(count):
        row = rows[a]
        scale = (np.exp(log_scales[row, 0]), np.exp(log_scales[row, 1]), np.exp(log_scales[row, 2]))
        out = starts[a]
        largest = opacity_logits[a, 0]
        for s in range(n):
            largest = max(largest, opacity_logits[a, s])
            if not opacity_logits[a, s] > 0:
                continue
            opacity = np.tanh(opacity_logits[a, s])
            for k in range(3):
                means[out, k] = positions[row, k] + offsets[row, s, k] * scale[k]
                factors[out, k] = _sigmoid(cov[a, 7 * s + k])
                scales[out, k] = scale[k] * factors[out, k]
                colors[out, k] = _sigmoid(color_logits[a, 3 * s + k])
            quats[out, 0] = cov[a, 7 * s + 3] + _ONE
            for k in range(1, 4):
                quats[out, k] = cov[a, 7 * s + 3 + k]
            opacities[out] = opacity
            kept_rows[out] = row
            slots[out] = s
            out += 1
        anchor_opacity[a] = np.tanh(largest)  # tanh is monotonic: the largest opacity
    return means, quats, scales, opacities, colors, kept_rows, slots, anchor_opacity, factors


@njit(cache=True, parallel=True, error_model="numpy")
def assemble_backward(opacity_logits, color_logits, cov, log_scales, offsets, rows, starts, slots,
                      opacities, colors, factors, grad_means, grad_quats, grad_scales, grad_opacities, grad_colors):
    """Chain rule of ``assemble_forward``: dense logit gradients (zero where a Gaussian was not
    kept) and full-size offset and log-scale gradients (zero outside the rows in view). The
    activations come from the forward (opacities, colours, scale factors), so nothing is recomputed
    but the anchor scale."""
    count = opacity_logits.shape[0]
    grad_opacity_logits = np.zeros_like(opacity_logits)
    grad_color_logits = np.zeros_like(color_logits)
    grad_cov = np.zeros_like(cov)
    grad_log_scales = np.zeros_like(log_scales)
    grad_offsets = np.zeros_like(offsets)
    for a in prange(count):
        row = rows[a]
        scale = (np.exp(log_scales[row, 0]), np.exp(log_scales[row, 1]), np.exp(log_scales[row, 2]))
        for out in range(starts[a], starts[a + 1]):
            s = slots[out]
            opacity = opacities[out]
            grad_opacity_logits[a, s] = grad_opacities[out] * (_ONE - opacity * opacity)
            for k in range(3):
                color = colors[out, k]
                grad_color_logits[a, 3 * s + k] = grad_colors[out, k] * (color * (_ONE - color))
                factor = factors[out, k]
                grad_cov[a, 7 * s + k] = grad_scales[out, k] * scale[k] * (factor * (_ONE - factor))
                grad_offsets[row, s, k] = grad_means[out, k] * scale[k]
                grad_log_scales[row, k] += grad_means[out, k] * offsets[row, s, k] + grad_scales[out, k] * factor
            for k in range(4):
                grad_cov[a, 7 * s + 3 + k] = grad_quats[out, k]
        for k in range(3):
            grad_log_scales[row, k] *= scale[k]  # d exp(x) / dx = exp(x)
    return grad_opacity_logits, grad_color_logits, grad_cov, grad_log_scales, grad_offsets


class AssembleGaussians(torch.autograd.Function):
    """(opacity logits, colour logits, covariance outputs, anchor tables, rows) -> kept Gaussians."""

    @staticmethod
    def forward(ctx, opacity_logits, color_logits, cov, positions, log_scales, offsets, rows):
        inputs = [float32_array(t) for t in (opacity_logits, color_logits, cov, positions, log_scales, offsets)]
        rows_np = np.ascontiguousarray(rows.numpy().astype(np.int64, copy=False))
        starts = _kept_starts(inputs[0])
        *outputs, factors = assemble_forward(*inputs, rows_np, starts)
        tensors = [torch.from_numpy(o) for o in outputs]
        ctx.state = (inputs, rows_np, starts, outputs[6], factors)
        # Opacities and colours are outputs the backward reads: saved so in-place edits are caught.
        ctx.save_for_backward(tensors[3], tensors[4])
        ctx.mark_non_differentiable(*tensors[5:])
        return tuple(tensors)

    @staticmethod
    def backward(ctx, grad_means, grad_quats, grad_scales, grad_opacities, grad_colors, *_unused):
        (opacity_logits, color_logits, cov, _positions, log_scales, offsets), rows, starts, slots, factors = ctx.state
        opacities, colors = (t.numpy() for t in ctx.saved_tensors)
        total = int(starts[-1])
        upstream = [
            np.zeros(shape, np.float32) if g is None else float32_array(g)
            for g, shape in ((grad_means, (total, 3)), (grad_quats, (total, 4)), (grad_scales, (total, 3)),
                             (grad_opacities, (total,)), (grad_colors, (total, 3)))
        ]
        grads = assemble_backward(opacity_logits, color_logits, cov, log_scales, offsets, rows, starts, slots,
                                  opacities, colors, factors, *upstream)
        g_opacity, g_color, g_cov, g_log_scales, g_offsets = (torch.from_numpy(g) for g in grads)
        return g_opacity, g_color, g_cov, None, g_log_scales, g_offsets, None
