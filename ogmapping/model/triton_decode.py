"""The static-shape decode of a window (``static_gaussians.generate_drawn``) as two Triton kernels: the GPU's
fused decode.

Through autograd the decode is some forty small operators each way (the inputs' concatenation, the three
MLPs' matmuls, the activations, the anchor scale and offsets, the drawn mask), each a kernel and most a
saved buffer of V x capacity x n rows. Here one kernel decodes every (row, view) pair of the window: a
program takes a block of anchor rows, one view and one of the three MLPs; it multiplies the rows' features
and their view direction and distance through the MLP in registers (the hidden layer never leaves the
program) and writes that MLP's outputs of every Gaussian of the block: opacity and the drawn flag, colour
and the mean, or scale and rotation. The backward kernel runs the forward again: a program takes one MLP
and blocks p, p + P, ... of the rows over every view of the window; it writes its part of the rows'
gradients (features, offsets, log-scales, colours) once, summed over the views, and its share of the
MLP's weight gradients, which the host sums over the programs in a fixed order (no atomics: the same bits
every run), as it sums the three MLPs' parts of the features' gradient.

The first layer's product with the features is the same in every view, so the backward makes it once a
block, and the gradients through it once from their sum over the views. The decoders' output columns keep
``nn.Linear``'s order (slot-major: colour ``3j + c``, covariance ``7j + k``), which is also the order of
the outputs' memory, so every store is one masked tile.

The camera centres and anchor centres are constants here (the step detaches its poses, the centres are a
buffer): the view direction and distance pass no gradient back, and the wrapper refuses either if it
requires one. The kernels are ``torch.library.triton_op`` operators with their autograd registered, so a
compiled graph (``ogmapping.mapping.graphs``) traces them as they are. Importing this module needs triton;
with ``TRITON_INTERPRET=1`` set before it is imported the kernels run on CPU tensors through Triton's
interpreter, as the tests run them.
"""

from __future__ import annotations

import torch
import triton
from torch.library import triton_op, wrap_triton

from ogmapping.model.decode_kernels import (
    BACKWARD_BLOCK,
    BLOCK,
    MAX_PROGRAMS,
    WARPS,
    backward_kernel,
    forward_kernel,
    padded,
)
from ogmapping.model.decoders import Decoders


def _sizes(features: torch.Tensor, w1o: torch.Tensor, n: int, block: int) -> dict[str, int]:
    """The kernels' widths, tile widths and warps."""
    width, hidden = features.shape[1], w1o.shape[0]
    return {"features": width, "hidden": hidden, "n": n, "num_warps": WARPS, "BLOCK": block, "F_PAD": padded(width),
            "H_PAD": padded(hidden), "NO_PAD": padded(n), "NC_PAD": padded(3 * n), "NV_PAD": padded(7 * n)}


@triton_op("ogmapping::fused_decode", mutates_args={})
def _fused_decode(features: torch.Tensor, positions: torch.Tensor, offsets: torch.Tensor, log_scales: torch.Tensor,
                  colours: torch.Tensor | None, centers: torch.Tensor, in_view: torch.Tensor,
                  w1o: torch.Tensor, b1o: torch.Tensor, w2o: torch.Tensor, b2o: torch.Tensor,
                  w1c: torch.Tensor, b1c: torch.Tensor, w2c: torch.Tensor, b2c: torch.Tensor,
                  w1v: torch.Tensor, b1v: torch.Tensor, w2v: torch.Tensor, b2v: torch.Tensor,
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor,
                             torch.Tensor]:
    """(C, ...) rows, (V, 3) centres, (V, C) in view -> means (V, C, n, 3), quats (V, C, n, 4), scales
    (V, C, n, 3), opacities (V, C, n), colours (V, C, n, 3), drawn (V, C, n) and anchor opacity (V, C)."""
    rows_count, n = offsets.shape[0], offsets.shape[1]
    views = centers.shape[0]
    outputs = (features.new_empty((views, rows_count, n, 3)), features.new_empty((views, rows_count, n, 4)),
               features.new_empty((views, rows_count, n, 3)), features.new_empty((views, rows_count, n)),
               features.new_empty((views, rows_count, n, 3)),
               torch.empty((views, rows_count, n), dtype=torch.bool, device=features.device),
               features.new_empty((views, rows_count)))
    if rows_count > 0 and views > 0:
        wrap_triton(forward_kernel)[(triton.cdiv(rows_count, BLOCK), views, 3)](
            features, positions, offsets, log_scales, features if colours is None else colours, centers, in_view,
            w1o, b1o, w2o, b2o, w1c, b1c, w2c, b2c, w1v, b1v, w2v, b2v, *outputs, rows_count,
            WITH_COLOURS=colours is not None, **_sizes(features, w1o, n, BLOCK))
    return outputs


@triton_op("ogmapping::fused_decode_backward", mutates_args={})
def _fused_decode_backward(grad_means: torch.Tensor, grad_quats: torch.Tensor, grad_scales: torch.Tensor,
                           grad_opacities: torch.Tensor, grad_colors: torch.Tensor, features: torch.Tensor,
                           positions: torch.Tensor, offsets: torch.Tensor, log_scales: torch.Tensor,
                           colours: torch.Tensor | None, centers: torch.Tensor, in_view: torch.Tensor,
                           w1o: torch.Tensor, b1o: torch.Tensor, w2o: torch.Tensor, b2o: torch.Tensor,
                           w1c: torch.Tensor, b1c: torch.Tensor, w2c: torch.Tensor, b2c: torch.Tensor,
                           w1v: torch.Tensor, b1v: torch.Tensor, w2v: torch.Tensor, b2v: torch.Tensor,
                           ) -> list[torch.Tensor]:
    """Gradients of the features, offsets, log-scales, colours (empty without them) and, flat, one after
    the other, of the twelve decoder weights, from those of the five decoded values."""
    rows_count, n = offsets.shape[0], offsets.shape[1]
    weights = (w1o, b1o, w2o, b2o, w1c, b1c, w2c, b2c, w1v, b1v, w2v, b2v)
    partial_size = sum(weight.numel() for weight in weights)
    programs = max(1, min(triton.cdiv(rows_count, BACKWARD_BLOCK), MAX_PROGRAMS))
    partials = features.new_empty((programs, partial_size))
    # each MLP's share of the features' gradient, and of the log-scales' through the means and the scales
    features_parts = features.new_empty((3, *features.shape))
    log_scales_parts = log_scales.new_empty((2, *log_scales.shape))
    offsets_grad = torch.empty_like(offsets)
    colours_grad = features.new_empty(0) if colours is None else torch.empty_like(colours)
    wrap_triton(backward_kernel)[(programs, 3)](
        features, positions, offsets, log_scales, features if colours is None else colours, centers, in_view,
        *weights, grad_means, grad_quats, grad_scales, grad_opacities, grad_colors, features_parts, offsets_grad,
        log_scales_parts, colours_grad, partials, rows_count, centers.shape[0], partial_size=partial_size,
        WITH_COLOURS=colours is not None, **_sizes(features, w1o, n, BACKWARD_BLOCK))
    return [features_parts.sum(dim=0), offsets_grad, log_scales_parts.sum(dim=0), colours_grad, partials.sum(dim=0)]


def _setup_context(ctx, inputs, output) -> None:
    ctx.with_colours = inputs[4] is not None
    ctx.save_for_backward(*inputs)
    ctx.mark_non_differentiable(output[5], output[6])


def _backward(ctx, grad_means, grad_quats, grad_scales, grad_opacities, grad_colors, _grad_drawn,
              _grad_anchor_opacity):
    grads = _fused_decode_backward(*(grad.contiguous() for grad in (grad_means, grad_quats, grad_scales,
                                                                    grad_opacities, grad_colors)),
                                   *ctx.saved_tensors)
    features, offsets, log_scales, colours, flat = grads
    weights = ctx.saved_tensors[7:]
    parts = flat.split([weight.numel() for weight in weights])
    return (features, None, offsets, log_scales, colours if ctx.with_colours else None, None, None,
            *(part.view(weight.shape) for part, weight in zip(parts, weights, strict=True)))


_fused_decode.register_autograd(_backward, setup_context=_setup_context)


def decode_window(features: torch.Tensor, positions: torch.Tensor, offsets: torch.Tensor, log_scales: torch.Tensor,
                  colours: torch.Tensor | None, camera_centers: torch.Tensor, in_view: torch.Tensor,
                  decoders: Decoders) -> tuple[torch.Tensor, ...]:
    """Every Gaussian of every buffer row in every view, as ``static_gaussians.generate_drawn`` decodes them:
    means, quats, scales, opacities (0 where not drawn), colours, drawn (V, C * n, ...) and each anchor's
    largest opacity (V, C). Rows: ``features`` (C, F), ``positions`` (C, 3), ``offsets`` (C, n, 3),
    ``log_scales`` (C, 3), ``colours`` (C, 3) logits or None; ``camera_centers`` (V, 3); ``in_view`` (V, C)
    bool. Differentiable in the rows other than ``positions`` and in the decoders' weights."""
    rows_count, n = offsets.shape[0], decoders.n
    if features.dtype != torch.float32:
        raise ValueError(f"the fused decode runs in float32, got {features.dtype}")
    if offsets.shape != (rows_count, n, 3) or features.shape[0] != rows_count or log_scales.shape != (rows_count, 3):
        raise ValueError(f"the fused decode takes rows of one count with {n} offsets each, got features "
                         f"{tuple(features.shape)}, offsets {tuple(offsets.shape)}, "
                         f"log-scales {tuple(log_scales.shape)}")
    if in_view.shape != (camera_centers.shape[0], rows_count):
        raise ValueError(f"the fused decode takes an in-view mask of (views, rows) = "
                         f"{(camera_centers.shape[0], rows_count)}, got {tuple(in_view.shape)}")
    if in_view.dtype != torch.bool:
        raise ValueError(f"the fused decode takes a bool in-view mask, got {in_view.dtype}")
    if positions.requires_grad or camera_centers.requires_grad:
        raise ValueError("the fused decode passes no gradient to the anchor or camera centres")
    weights = [tensor.contiguous() for mlp in (decoders.opacity, decoders.color, decoders.cov)
               for tensor in (mlp[0].weight, mlp[0].bias, mlp[2].weight, mlp[2].bias)]
    outputs = _fused_decode(features.contiguous(), positions.contiguous(), offsets.contiguous(),
                            log_scales.contiguous(), None if colours is None else colours.contiguous(),
                            camera_centers.to(positions).contiguous(), in_view.contiguous(), *weights)
    views, per_view = in_view.shape[0], rows_count * n
    means, quats, scales, opacities, colors, drawn, anchor_opacity = outputs
    return (means.view(views, per_view, 3), quats.view(views, per_view, 4), scales.view(views, per_view, 3),
            opacities.view(views, per_view), colors.view(views, per_view, 3), drawn.view(views, per_view),
            anchor_opacity)
