"""The Triton kernels of the fused decode (``ogmapping.model.triton_decode`` explains them and wraps them
as torch operators): the forward over every (row block, view, MLP), the backward over blocks of rows with
each MLP's weight gradients as per-program partial rows."""

from __future__ import annotations

import triton
import triton.language as tl

# The products in float32 on the CUDA cores, as torch's reference multiplies (TF32 off): at these widths
# (K = 16 to 64) tensor cores would gain little, and their operand tiles took registers the backward spilled.
DOT_PRECISION: tl.constexpr = tl.constexpr("ieee")
BLOCK = 32  # anchor rows a forward program decodes
BACKWARD_BLOCK = 16  # and a backward program at a time: it holds more tiles
WARPS = 8  # per program: with four, the backward's tiles spilled out of the registers (sm_90, at n = 5)
MAX_PROGRAMS = 1024  # backward programs: each sums the weight gradients of its blocks into one partial row


def padded(width: int) -> int:
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
def forward_kernel(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
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
def backward_kernel(features_ptr, positions_ptr, offsets_ptr, log_scales_ptr, colours_ptr, centers_ptr, in_view_ptr,
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
