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
import triton.language as tl
from torch.library import triton_op, wrap_triton

from ogmapping.model.decoders import Decoders

# The products in float32 on the CUDA cores, as torch's reference multiplies (TF32 off): at these widths
# (K = 16 to 64) tensor cores would gain little, and their operand tiles took registers the backward spilled.
DOT_PRECISION: tl.constexpr = tl.constexpr("ieee")
BLOCK = 32  # anchor rows a forward program decodes
BACKWARD_BLOCK = 16  # and a backward program at a time: it holds more tiles
WARPS = 8  # per program: with four, the backward's tiles spilled out of the registers (sm_90, at n = 5)
MAX_PROGRAMS = 1024  # backward programs: each sums the weight gradients of its blocks into one partial row


def _padded(width: int) -> int:
    """A tile's width: a power of two, and at least 16, the least ``tl.dot`` takes."""
    return max(16, triton.next_power_of_2(width))


@triton.jit
def _tanh(x):
    """tanh, by its series where |x| < 1/16: there the exponential form loses digits to cancellation."""
    magnitude = tl.abs(x)
    e = tl.exp(-2.0 * magnitude)
    exponential = (1.0 - e) / (1.0 + e)
    square = magnitude * magnitude
    series = magnitude * (1.0 - square * (1.0 / 3.0 - square * (2.0 / 15.0)))
    value = tl.where(magnitude < 0.0625, series, exponential)
    return tl.where(x < 0, -value, value)


@triton.jit
def _width(n, KIND: tl.constexpr):
    """The outputs of MLP KIND (0: opacity, 1: colour, 2: covariance): n, 3n, 7n."""
    if KIND == 0:
        width = n
    elif KIND == 1:
        width = 3 * n
    else:
        width = 7 * n
    return width


@triton.jit
def _weights(w1_ptr, b1_ptr, w2_ptr, b2_ptr, features, hidden, width, f_cols, hidden_cols, cols):
    """One MLP's weights, transposed for the products: W1's feature columns (F_PAD, H_PAD), its four
    geometry columns (H_PAD,), b1, W2 (H_PAD, OUT_PAD) and b2."""
    in_dim = features + 4
    hidden_ok = hidden_cols < hidden
    w1f = tl.load(w1_ptr + hidden_cols[None, :] * in_dim + f_cols[:, None],
                  mask=(f_cols[:, None] < features) & hidden_ok[None, :], other=0.0)
    g0 = tl.load(w1_ptr + hidden_cols * in_dim + features, mask=hidden_ok, other=0.0)
    g1 = tl.load(w1_ptr + hidden_cols * in_dim + features + 1, mask=hidden_ok, other=0.0)
    g2 = tl.load(w1_ptr + hidden_cols * in_dim + features + 2, mask=hidden_ok, other=0.0)
    g3 = tl.load(w1_ptr + hidden_cols * in_dim + features + 3, mask=hidden_ok, other=0.0)
    b1 = tl.load(b1_ptr + hidden_cols, mask=hidden_ok, other=0.0)
    w2 = tl.load(w2_ptr + cols[None, :] * hidden + hidden_cols[:, None],
                 mask=hidden_ok[:, None] & (cols[None, :] < width), other=0.0)
    b2 = tl.load(b2_ptr + cols, mask=cols < width, other=0.0)
    return w1f, g0, g1, g2, g3, b1, w2, b2


@triton.jit
def _features(features_ptr, rows, row_ok, f_cols, features):
    return tl.load(features_ptr + rows[:, None] * features + f_cols[None, :],
                   mask=row_ok[:, None] & (f_cols[None, :] < features), other=0.0)


@triton.jit
def _geometry(positions_ptr, centers_ptr, view, rows, row_ok):
    """The unit direction from each row's centre to the camera of ``view`` and the distance to it, the
    decoders' last four inputs (``gaussians.decoded_logits``)."""
    tx = tl.load(centers_ptr + view * 3) - tl.load(positions_ptr + rows * 3, mask=row_ok, other=0.0)
    ty = tl.load(centers_ptr + view * 3 + 1) - tl.load(positions_ptr + rows * 3 + 1, mask=row_ok, other=0.0)
    tz = tl.load(centers_ptr + view * 3 + 2) - tl.load(positions_ptr + rows * 3 + 2, mask=row_ok, other=0.0)
    distance = tl.maximum(tl.sqrt_rn(tx * tx + ty * ty + tz * tz), 1e-6)
    return tx / distance, ty / distance, tz / distance, distance


@triton.jit
def _hidden(feature_part, g0, g1, g2, g3, dx, dy, dz, distance):
    """The hidden pre-activation: the features' part (their product with W1, plus b1) and the geometry's."""
    return (feature_part + dx[:, None] * g0[None, :] + dy[:, None] * g1[None, :] + dz[:, None] * g2[None, :]
            + distance[:, None] * g3[None, :])


@triton.jit
def _three_tables(offsets_ptr, log_scales_ptr, colours_ptr, positions_ptr, rows, three_ok, three_cols, n,
                  WITH_COLOURS: tl.constexpr):
    """Per row, in the colour and mean columns (3j + c): the offset, the anchor scale, the anchor colour and
    the centre's coordinate."""
    axis = three_cols[None, :] % 3
    offsets = tl.load(offsets_ptr + rows[:, None] * 3 * n + three_cols[None, :], mask=three_ok, other=0.0)
    scale = tl.exp(tl.load(log_scales_ptr + rows[:, None] * 3 + axis, mask=three_ok, other=0.0))
    colour = tl.zeros_like(scale)
    if WITH_COLOURS:
        colour = tl.load(colours_ptr + rows[:, None] * 3 + axis, mask=three_ok, other=0.0)
    centre = tl.load(positions_ptr + rows[:, None] * 3 + axis, mask=three_ok, other=0.0)
    return offsets, scale, colour, centre


@triton.jit
def _cov_scale(log_scales_ptr, rows, cov_ok, k):
    """Per row, in the covariance columns (7j + k): the anchor scale of axis k < 3, else 0."""
    return tl.where(k < 3, tl.exp(tl.load(log_scales_ptr + rows[:, None] * 3 + k, mask=cov_ok & (k < 3),
                                          other=0.0)), 0.0)


@triton.jit
def _forward_part(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
                  w1_ptr, b1_ptr, w2_ptr, b2_ptr, means_ptr, quats_ptr, scales_ptr, opacities_ptr, colors_ptr,
                  drawn_ptr, anchor_opacity_ptr, rows_count, features, hidden, n, KIND: tl.constexpr,
                  WITH_COLOURS: tl.constexpr, BLOCK: tl.constexpr, F_PAD: tl.constexpr, H_PAD: tl.constexpr,
                  OUT_PAD: tl.constexpr):
    """MLP KIND's outputs of a block of rows in one view (0: opacity and drawn, 1: colour and the means,
    2: scale and rotation)."""
    view = tl.program_id(1)
    rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    row_ok = rows < rows_count
    f_cols, hidden_cols, cols = tl.arange(0, F_PAD), tl.arange(0, H_PAD), tl.arange(0, OUT_PAD)
    width = _width(n, KIND)
    w1f, g0, g1, g2, g3, b1, w2, b2 = _weights(w1_ptr, b1_ptr, w2_ptr, b2_ptr, features, hidden, width, f_cols,
                                               hidden_cols, cols)
    feature_part = tl.dot(_features(features_ptr, rows, row_ok, f_cols, features), w1f,
                          input_precision=DOT_PRECISION) + b1[None, :]
    dx, dy, dz, distance = _geometry(positions_ptr, centers_ptr, view, rows, row_ok)
    pre = _hidden(feature_part, g0, g1, g2, g3, dx, dy, dz, distance)
    out = tl.dot(tl.maximum(pre, 0.0), w2, input_precision=DOT_PRECISION) + b2[None, :]
    anchor_rows = (view * rows_count + rows).to(tl.int64)  # the (V, C) index of each row
    anchor = anchor_rows[:, None]
    ok = row_ok[:, None] & (cols[None, :] < width)
    if KIND == 0:
        in_view = tl.load(in_view_ptr + anchor_rows, mask=row_ok, other=0) != 0
        drawn = (out > 0.0) & in_view[:, None]
        value = _tanh(out)
        tl.store(opacities_ptr + anchor * n + cols[None, :], tl.where(drawn, value, 0.0), mask=ok)
        tl.store(drawn_ptr + anchor * n + cols[None, :], drawn, mask=ok)
        tl.store(anchor_opacity_ptr + anchor_rows, tl.max(tl.where(cols[None, :] < n, value, float("-inf")), 1),
                 mask=row_ok)
    elif KIND == 1:
        offsets, scale, anchor_colour, centre = _three_tables(offsets_ptr, log_scales_ptr, colours_ptr,
                                                              positions_ptr, rows, ok, cols, n, WITH_COLOURS)
        at = anchor * 3 * n + cols[None, :]
        tl.store(colors_ptr + at, tl.sigmoid(out + anchor_colour), mask=ok)
        tl.store(means_ptr + at, centre + offsets * scale, mask=ok)
    else:
        k = cols[None, :] % 7
        gaussian = anchor * n + cols[None, :] // 7
        scale = _cov_scale(log_scales_ptr, rows, ok, k)
        tl.store(scales_ptr + gaussian * 3 + k, scale * tl.sigmoid(out), mask=ok & (k < 3))
        tl.store(quats_ptr + gaussian * 4 + k - 3, out + tl.where(k == 3, 1.0, 0.0), mask=ok & (k >= 3))


@triton.jit
def _forward_kernel(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
                    w1o, b1o, w2o, b2o, w1c, b1c, w2c, b2c, w1v, b1v, w2v, b2v,
                    means_ptr, quats_ptr, scales_ptr, opacities_ptr, colors_ptr, drawn_ptr, anchor_opacity_ptr,
                    rows_count, features, hidden, n, WITH_COLOURS: tl.constexpr, BLOCK: tl.constexpr,
                    F_PAD: tl.constexpr, H_PAD: tl.constexpr, NO_PAD: tl.constexpr, NC_PAD: tl.constexpr,
                    NV_PAD: tl.constexpr):
    """Program (block, view, MLP): ``_forward_part``."""
    kind = tl.program_id(2)
    if kind == 0:
        _forward_part(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
                      w1o, b1o, w2o, b2o, means_ptr, quats_ptr, scales_ptr, opacities_ptr, colors_ptr, drawn_ptr,
                      anchor_opacity_ptr, rows_count, features, hidden, n, 0, WITH_COLOURS, BLOCK, F_PAD, H_PAD,
                      NO_PAD)
    elif kind == 1:
        _forward_part(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
                      w1c, b1c, w2c, b2c, means_ptr, quats_ptr, scales_ptr, opacities_ptr, colors_ptr, drawn_ptr,
                      anchor_opacity_ptr, rows_count, features, hidden, n, 1, WITH_COLOURS, BLOCK, F_PAD, H_PAD,
                      NC_PAD)
    else:
        _forward_part(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
                      w1v, b1v, w2v, b2v, means_ptr, quats_ptr, scales_ptr, opacities_ptr, colors_ptr, drawn_ptr,
                      anchor_opacity_ptr, rows_count, features, hidden, n, 2, WITH_COLOURS, BLOCK, F_PAD, H_PAD,
                      NV_PAD)


@triton.jit
def _backward_part(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
                   w1_ptr, b1_ptr, w2_ptr, b2_ptr, grad_means_ptr, grad_quats_ptr, grad_scales_ptr,
                   grad_opacities_ptr, grad_colors_ptr, grad_features_ptr, grad_offsets_ptr, grad_log_scales_ptr,
                   grad_colours_ptr, partial_ptr, rows_count, views, features, hidden, n,
                   KIND: tl.constexpr, WITH_COLOURS: tl.constexpr, BLOCK: tl.constexpr, F_PAD: tl.constexpr,
                   H_PAD: tl.constexpr, OUT_PAD: tl.constexpr):
    """MLP KIND's share of the backward (KIND as ``_forward_part``) for blocks p, p + P, ... of the rows: its
    part of the features' gradient (and KIND 1: the offsets', the colours' and the log-scales' through the
    means; KIND 2: the log-scales' through the scales), summed over the views, and its weights' gradients
    summed over those blocks, at ``partial_ptr``. The features' part of the first layer is the same in
    every view: it is multiplied out once a block, and its gradients once from their sum over the views."""
    f_cols, hidden_cols, cols = tl.arange(0, F_PAD), tl.arange(0, H_PAD), tl.arange(0, OUT_PAD)
    width = _width(n, KIND)
    w1f, g0, g1, g2, g3, b1, w2, b2 = _weights(w1_ptr, b1_ptr, w2_ptr, b2_ptr, features, hidden, width, f_cols,
                                               hidden_cols, cols)
    d_w1f = tl.zeros((F_PAD, H_PAD), tl.float32)
    d_g0, d_g1 = tl.zeros((H_PAD,), tl.float32), tl.zeros((H_PAD,), tl.float32)
    d_g2, d_g3 = tl.zeros((H_PAD,), tl.float32), tl.zeros((H_PAD,), tl.float32)
    d_b1 = tl.zeros((H_PAD,), tl.float32)
    d_w2 = tl.zeros((H_PAD, OUT_PAD), tl.float32)
    d_b2 = tl.zeros((OUT_PAD,), tl.float32)
    k = cols[None, :] % 7
    axis = cols[None, :] % 3
    for block in range(tl.program_id(0), tl.cdiv(rows_count, BLOCK), tl.num_programs(0)):
        rows = block * BLOCK + tl.arange(0, BLOCK)
        row_ok = rows < rows_count
        ok = row_ok[:, None] & (cols[None, :] < width)
        feature = _features(features_ptr, rows, row_ok, f_cols, features)
        feature_part = tl.dot(feature, w1f, input_precision=DOT_PRECISION) + b1[None, :]
        if KIND == 1:
            offsets, scale, anchor_colour, _ = _three_tables(offsets_ptr, log_scales_ptr, colours_ptr, positions_ptr,
                                                             rows, ok, cols, n, WITH_COLOURS)
        elif KIND == 2:
            scale = _cov_scale(log_scales_ptr, rows, ok, k)
        d_pre_sum = tl.zeros((BLOCK, H_PAD), tl.float32)
        d_sum = tl.zeros((BLOCK, OUT_PAD), tl.float32)  # KIND 1: d colour logits; 2: d scales * scales
        d_mean_sum = tl.zeros((BLOCK, OUT_PAD), tl.float32)  # KIND 1: d means
        for view in range(views):
            dx, dy, dz, distance = _geometry(positions_ptr, centers_ptr, view, rows, row_ok)
            pre = _hidden(feature_part, g0, g1, g2, g3, dx, dy, dz, distance)
            hidden_out = tl.maximum(pre, 0.0)
            out = tl.dot(hidden_out, w2, input_precision=DOT_PRECISION) + b2[None, :]
            anchor = (view * rows_count + rows).to(tl.int64)[:, None]
            if KIND == 0:
                in_view = tl.load(in_view_ptr + view * rows_count + rows, mask=row_ok, other=0) != 0
                value = _tanh(out)
                grad = tl.load(grad_opacities_ptr + anchor * n + cols[None, :], mask=ok, other=0.0)
                d_out = tl.where((out > 0.0) & in_view[:, None], grad * (1.0 - value * value), 0.0)
            elif KIND == 1:
                at = anchor * 3 * n + cols[None, :]
                value = tl.sigmoid(out + anchor_colour)
                d_out = tl.load(grad_colors_ptr + at, mask=ok, other=0.0) * value * (1.0 - value)
                d_sum += d_out
                d_mean_sum += tl.load(grad_means_ptr + at, mask=ok, other=0.0)
            else:
                gaussian = anchor * n + cols[None, :] // 7
                grad_scale = tl.load(grad_scales_ptr + gaussian * 3 + k, mask=ok & (k < 3), other=0.0)
                grad_quat = tl.load(grad_quats_ptr + gaussian * 4 + k - 3, mask=ok & (k >= 3), other=0.0)
                factor = tl.sigmoid(out)
                d_scaled = grad_scale * scale * factor
                d_sum += d_scaled
                d_out = tl.where(k < 3, d_scaled * (1.0 - factor), grad_quat)
            d_pre = tl.where(pre > 0.0, tl.dot(d_out, tl.trans(w2), input_precision=DOT_PRECISION), 0.0)
            d_pre_sum += d_pre
            d_g0 += tl.sum(d_pre * dx[:, None], 0)
            d_g1 += tl.sum(d_pre * dy[:, None], 0)
            d_g2 += tl.sum(d_pre * dz[:, None], 0)
            d_g3 += tl.sum(d_pre * distance[:, None], 0)
            d_w2 += tl.dot(tl.trans(hidden_out), d_out, input_precision=DOT_PRECISION)
            d_b2 += tl.sum(d_out, 0)
        d_w1f += tl.dot(tl.trans(feature), d_pre_sum, input_precision=DOT_PRECISION)
        d_b1 += tl.sum(d_pre_sum, 0)
        tl.store(grad_features_ptr + KIND * rows_count * features + rows[:, None] * features + f_cols[None, :],
                 tl.dot(d_pre_sum, tl.trans(w1f), input_precision=DOT_PRECISION),
                 mask=row_ok[:, None] & (f_cols[None, :] < features))
        if KIND == 1:
            tl.store(grad_offsets_ptr + rows[:, None] * 3 * n + cols[None, :], d_mean_sum * scale, mask=ok)
            for c in tl.static_range(3):
                tl.store(grad_log_scales_ptr + rows * 3 + c,
                         tl.sum(tl.where(axis == c, d_mean_sum * offsets * scale, 0.0), 1), mask=row_ok)
                if WITH_COLOURS:
                    tl.store(grad_colours_ptr + rows * 3 + c, tl.sum(tl.where(axis == c, d_sum, 0.0), 1), mask=row_ok)
        elif KIND == 2:
            for c in tl.static_range(3):
                tl.store(grad_log_scales_ptr + (rows_count + rows) * 3 + c, tl.sum(tl.where(k == c, d_sum, 0.0), 1),
                         mask=row_ok)
    # nn.Linear's layouts, one after the other: W1 (its feature columns, then the geometry's), b1, W2, b2
    in_dim = features + 4
    hidden_ok = hidden_cols < hidden
    tl.store(partial_ptr + hidden_cols[None, :] * in_dim + f_cols[:, None], d_w1f,
             mask=(f_cols[:, None] < features) & hidden_ok[None, :])
    tl.store(partial_ptr + hidden_cols * in_dim + features, d_g0, mask=hidden_ok)
    tl.store(partial_ptr + hidden_cols * in_dim + features + 1, d_g1, mask=hidden_ok)
    tl.store(partial_ptr + hidden_cols * in_dim + features + 2, d_g2, mask=hidden_ok)
    tl.store(partial_ptr + hidden_cols * in_dim + features + 3, d_g3, mask=hidden_ok)
    partial_ptr += hidden * in_dim
    tl.store(partial_ptr + hidden_cols, d_b1, mask=hidden_ok)
    partial_ptr += hidden
    tl.store(partial_ptr + cols[None, :] * hidden + hidden_cols[:, None], d_w2,
             mask=hidden_ok[:, None] & (cols[None, :] < width))
    tl.store(partial_ptr + width * hidden + cols, d_b2, mask=cols < width)


@triton.jit
def _backward_kernel(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
                     w1o, b1o, w2o, b2o, w1c, b1c, w2c, b2c, w1v, b1v, w2v, b2v,
                     grad_means_ptr, grad_quats_ptr, grad_scales_ptr, grad_opacities_ptr, grad_colors_ptr,
                     grad_features_ptr, grad_offsets_ptr, grad_log_scales_ptr, grad_colours_ptr, partials_ptr,
                     rows_count, views, features, hidden, n, partial_size, WITH_COLOURS: tl.constexpr,
                     BLOCK: tl.constexpr, F_PAD: tl.constexpr, H_PAD: tl.constexpr, NO_PAD: tl.constexpr,
                     NC_PAD: tl.constexpr, NV_PAD: tl.constexpr):
    """Program (p, MLP): ``_backward_part`` of that MLP; its weights' gradients go to partial row p, in the
    MLPs' order (opacity, colour, covariance)."""
    first_layer = hidden * (features + 4) + hidden
    opacity_size = first_layer + n * (hidden + 1)
    colour_size = first_layer + 3 * n * (hidden + 1)
    partial_ptr = partials_ptr + tl.program_id(0).to(tl.int64) * partial_size
    kind = tl.program_id(1)
    if kind == 0:
        _backward_part(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr,
                       in_view_ptr, w1o, b1o, w2o, b2o, grad_means_ptr, grad_quats_ptr, grad_scales_ptr,
                       grad_opacities_ptr, grad_colors_ptr, grad_features_ptr, grad_offsets_ptr, grad_log_scales_ptr,
                       grad_colours_ptr, partial_ptr, rows_count, views, features, hidden, n, 0, WITH_COLOURS,
                       BLOCK, F_PAD, H_PAD, NO_PAD)
    elif kind == 1:
        _backward_part(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr,
                       in_view_ptr, w1c, b1c, w2c, b2c, grad_means_ptr, grad_quats_ptr, grad_scales_ptr,
                       grad_opacities_ptr, grad_colors_ptr, grad_features_ptr, grad_offsets_ptr, grad_log_scales_ptr,
                       grad_colours_ptr, partial_ptr + opacity_size, rows_count, views, features, hidden, n, 1,
                       WITH_COLOURS, BLOCK, F_PAD, H_PAD, NC_PAD)
    else:
        _backward_part(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr,
                       in_view_ptr, w1v, b1v, w2v, b2v, grad_means_ptr, grad_quats_ptr, grad_scales_ptr,
                       grad_opacities_ptr, grad_colors_ptr, grad_features_ptr, grad_offsets_ptr, grad_log_scales_ptr,
                       grad_colours_ptr, partial_ptr + opacity_size + colour_size, rows_count, views, features,
                       hidden, n, 2, WITH_COLOURS, BLOCK, F_PAD, H_PAD, NV_PAD)


def _sizes(features: torch.Tensor, w1o: torch.Tensor, n: int, block: int) -> dict[str, int]:
    """The kernels' widths, tile widths and warps."""
    width, hidden = features.shape[1], w1o.shape[0]
    return {"features": width, "hidden": hidden, "n": n, "num_warps": WARPS, "BLOCK": block, "F_PAD": _padded(width),
            "H_PAD": _padded(hidden), "NO_PAD": _padded(n), "NC_PAD": _padded(3 * n), "NV_PAD": _padded(7 * n)}


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
        wrap_triton(_forward_kernel)[(triton.cdiv(rows_count, BLOCK), views, 3)](
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
    wrap_triton(_backward_kernel)[(programs, 3)](
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
