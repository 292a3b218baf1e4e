"""Numba kernels of the cpu rasterizer: tile binning, front-to-back forward, back-to-front backward.

All per-pixel arithmetic is float32 with float32 constants (a float64 literal would silently
promote the hot loops). ``fastmath`` stays off so the backward recomputes exactly the alphas the
forward used. Work is split by tile; every write goes to memory owned by the tile (its pixels, its
slice of the pair list), and per-Gaussian gradients are reduced from per-pair buffers afterwards,
so the kernels are race-free and deterministic whatever the thread count.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ogmapping.render import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN

TILE = 16
# Gradient columns per Gaussian: mean x, mean y, conic a, b, c, opacity, colour r, g, b, depth.
N_GRAD = 10

_ALPHA_MIN = np.float32(ALPHA_MIN)
_ALPHA_MAX = np.float32(ALPHA_MAX)
_T_MIN = np.float32(TRANSMITTANCE_MIN)
_HALF = np.float32(0.5)
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)
# Added to the exact log-threshold before skipping a Gaussian without evaluating exp(); far larger
# than float32 rounding, so the skip never removes a Gaussian the alpha test would keep.
_POWER_SLACK = np.float32(1e-3)


@njit(parallel=True, cache=True)
def bin_tiles(order, means2d, radii, width, height, n_chunks):
    """Tile lists of the Gaussians ``order`` (visible ones, front to back) as CSR arrays.

    Returns ``tile_offsets`` (n_tiles + 1), ``ids`` (pairs, Gaussian index per tile entry, each
    tile's slice front to back), and ``pair_start``/``pair_of`` which map the k-th Gaussian of
    ``order`` to its entries, for the gradient reduction. A counting sort over contiguous chunks
    of ``order`` keeps depth order inside every tile.
    """
    n = order.shape[0]
    n_x = (width + TILE - 1) // TILE
    n_y = (height + TILE - 1) // TILE
    n_tiles = n_x * n_y
    rects = np.zeros((n, 4), np.int64)
    counts = np.zeros(n, np.int64)
    for k in prange(n):
        g = order[k]
        r = np.float64(radii[g])
        u = np.float64(means2d[g, 0])
        v = np.float64(means2d[g, 1])
        x0 = max(np.floor((u - r) / TILE), 0.0)
        y0 = max(np.floor((v - r) / TILE), 0.0)
        x1 = min(np.floor((u + r) / TILE), n_x - 1.0)
        y1 = min(np.floor((v + r) / TILE), n_y - 1.0)
        if r > 0 and x1 >= x0 and y1 >= y0:
            rects[k, 0] = np.int64(x0)
            rects[k, 1] = np.int64(y0)
            rects[k, 2] = np.int64(x1)
            rects[k, 3] = np.int64(y1)
            counts[k] = (rects[k, 2] - rects[k, 0] + 1) * (rects[k, 3] - rects[k, 1] + 1)

    tile_counts = np.zeros((n_chunks, n_tiles), np.int64)
    for c in prange(n_chunks):
        for k in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            if counts[k] > 0:
                for ty in range(rects[k, 1], rects[k, 3] + 1):
                    for tx in range(rects[k, 0], rects[k, 2] + 1):
                        tile_counts[c, ty * n_x + tx] += 1

    tile_offsets = np.zeros(n_tiles + 1, np.int64)
    cursor = np.zeros((n_chunks, n_tiles), np.int64)
    total = 0
    for t in range(n_tiles):
        tile_offsets[t] = total
        for c in range(n_chunks):
            cursor[c, t] = total
            total += tile_counts[c, t]
    tile_offsets[n_tiles] = total
    pair_start = np.zeros(n + 1, np.int64)
    for k in range(n):
        pair_start[k + 1] = pair_start[k] + counts[k]

    ids = np.zeros(total, np.int32)
    pair_of = np.zeros(total, np.int64)
    for c in prange(n_chunks):
        for k in range(c * n // n_chunks, (c + 1) * n // n_chunks):
            p = pair_start[k]
            if counts[k] > 0:
                for ty in range(rects[k, 1], rects[k, 3] + 1):
                    for tx in range(rects[k, 0], rects[k, 2] + 1):
                        t = ty * n_x + tx
                        ids[cursor[c, t]] = order[k]
                        pair_of[p] = cursor[c, t]
                        cursor[c, t] += 1
                        p += 1
    return tile_offsets, ids, pair_start, pair_of


@njit(cache=True)
def _gather(ids, start, end, means2d, conics, opacities, x0, y0, tile_w, tile_h):
    """One tile's Gaussians, front to back, as contiguous rows with their pixel rectangles.

    Row k: mean x, mean y, conic a, b, c, opacity, skip threshold on ``power``. ``rects[k]`` is
    the inclusive local pixel range (x0, x1, y0, y1) whose centres lie within the bounding box of
    the ellipse ``power <= threshold``, padded by half a pixel; an empty range has x1 < x0.
    """
    g = end - start
    feats = np.empty((g, 7), np.float32)
    rects = np.empty((g, 4), np.int32)
    for k in range(g):
        idx = ids[start + k]
        o = opacities[idx]
        mx = means2d[idx, 0]
        my = means2d[idx, 1]
        a = conics[idx, 0]
        b = conics[idx, 1]
        c = conics[idx, 2]
        limit = np.log(o / _ALPHA_MIN) + _POWER_SLACK
        feats[k, 0] = mx
        feats[k, 1] = my
        feats[k, 2] = a
        feats[k, 3] = b
        feats[k, 4] = c
        feats[k, 5] = o
        feats[k, 6] = limit
        det = np.float64(a) * np.float64(c) - np.float64(b) * np.float64(b)
        lo_x, hi_x, lo_y, hi_y = 0, tile_w - 1, 0, tile_h - 1
        if det > 0.0 and limit > 0.0:
            ex = np.sqrt(2.0 * np.float64(limit) * np.float64(c) / det) + 0.5
            ey = np.sqrt(2.0 * np.float64(limit) * np.float64(a) / det) + 0.5
            lo_x = max(lo_x, np.int64(max(np.ceil(mx - ex - 0.5) - x0, -1.0)))
            hi_x = min(hi_x, np.int64(min(np.floor(mx + ex - 0.5) - x0, tile_w + 0.0)))
            lo_y = max(lo_y, np.int64(max(np.ceil(my - ey - 0.5) - y0, -1.0)))
            hi_y = min(hi_y, np.int64(min(np.floor(my + ey - 0.5) - y0, tile_h + 0.0)))
        elif limit <= 0.0:
            hi_x = -1
        rects[k, 0] = lo_x
        rects[k, 1] = hi_x
        rects[k, 2] = lo_y
        rects[k, 3] = hi_y
    return feats, rects


@njit(parallel=True, cache=True)
def render_forward(tile_offsets, ids, means2d, conics, opacities, colors, depths, background, width, height):
    """Composite every pixel front to back.

    Each tile walks its Gaussians in depth order and updates only the pixels inside each one's
    rectangle, keeping per-pixel state; this visits far fewer (pixel, Gaussian) pairs than a
    per-pixel scan of the whole tile list and gives the same per-pixel order. Returns colour over
    ``background`` (H, W, 3), accumulated depth (H, W), final transmittance (H, W) and, per pixel,
    the length of the tile-list prefix the backward has to revisit.
    """
    n_x = (width + TILE - 1) // TILE
    n_tiles = n_x * ((height + TILE - 1) // TILE)
    out_color = np.empty((height, width, 3), np.float32)
    out_depth = np.empty((height, width), np.float32)
    out_t = np.empty((height, width), np.float32)
    n_contrib = np.empty((height, width), np.int32)
    for t in prange(n_tiles):
        ty = t // n_x
        x0 = (t - ty * n_x) * TILE
        y0 = ty * TILE
        tile_w = min(TILE, width - x0)
        tile_h = min(TILE, height - y0)
        start = tile_offsets[t]
        feats, rects = _gather(ids, start, tile_offsets[t + 1], means2d, conics, opacities, x0, y0, tile_w, tile_h)
        trans = np.ones(TILE * TILE, np.float32)
        acc = np.zeros((TILE * TILE, 4), np.float32)
        last = np.zeros(TILE * TILE, np.int32)
        done = np.zeros(TILE * TILE, np.bool_)
        n_open = tile_w * tile_h
        for k in range(feats.shape[0]):
            if n_open == 0:
                break
            if rects[k, 1] < rects[k, 0] or rects[k, 3] < rects[k, 2]:
                continue
            mx = feats[k, 0]
            my = feats[k, 1]
            ca = feats[k, 2]
            cb = feats[k, 3]
            cc = feats[k, 4]
            o = feats[k, 5]
            limit = feats[k, 6]
            idx = ids[start + k]
            col0 = colors[idx, 0]
            col1 = colors[idx, 1]
            col2 = colors[idx, 2]
            z = depths[idx]
            for ly in range(rects[k, 2], rects[k, 3] + 1):
                dy = np.float32(y0 + ly) + _HALF - my
                for lx in range(rects[k, 0], rects[k, 1] + 1):
                    p = ly * TILE + lx
                    if done[p]:
                        continue
                    dx = np.float32(x0 + lx) + _HALF - mx
                    power = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if power > limit:
                        continue
                    alpha = min(_ALPHA_MAX, o * np.exp(-power))
                    if alpha < _ALPHA_MIN:
                        continue
                    t_now = trans[p]
                    next_t = t_now * (_ONE - alpha)
                    if next_t < _T_MIN:
                        done[p] = True
                        n_open -= 1
                        continue
                    w = alpha * t_now
                    acc[p, 0] += w * col0
                    acc[p, 1] += w * col1
                    acc[p, 2] += w * col2
                    acc[p, 3] += w * z
                    trans[p] = next_t
                    last[p] = k + 1
        for ly in range(tile_h):
            for lx in range(tile_w):
                p = ly * TILE + lx
                py = y0 + ly
                px = x0 + lx
                out_color[py, px, 0] = acc[p, 0] + trans[p] * background[0]
                out_color[py, px, 1] = acc[p, 1] + trans[p] * background[1]
                out_color[py, px, 2] = acc[p, 2] + trans[p] * background[2]
                out_depth[py, px] = acc[p, 3]
                out_t[py, px] = trans[p]
                n_contrib[py, px] = last[p]
    return out_color, out_depth, out_t, n_contrib


@njit(parallel=True, cache=True)
def render_backward(
    tile_offsets, ids, means2d, conics, opacities, colors, depths, background,
    final_t, n_contrib, grad_color, grad_depth, grad_alpha, width, height,
):
    """Gradients per tile entry (pairs, N_GRAD) and per tile for the background (n_tiles, 3).

    Walks each tile's Gaussians back to front over their rectangles; every pixel recovers the
    transmittance before each contributor as ``T / (1 - alpha)`` and keeps the colour and depth
    composited behind it as running sums. A Gaussian's gradient is summed over its pixels in
    registers and written once to its own tile entry.
    """
    n_x = (width + TILE - 1) // TILE
    n_tiles = n_x * ((height + TILE - 1) // TILE)
    pair_grads = np.zeros((tile_offsets[n_tiles], N_GRAD), np.float32)
    bg_grads = np.zeros((n_tiles, 3), np.float32)
    for t in prange(n_tiles):
        ty = t // n_x
        x0 = (t - ty * n_x) * TILE
        y0 = ty * TILE
        tile_w = min(TILE, width - x0)
        tile_h = min(TILE, height - y0)
        start = tile_offsets[t]
        feats, rects = _gather(ids, start, tile_offsets[t + 1], means2d, conics, opacities, x0, y0, tile_w, tile_h)
        # Per pixel: T, colour/depth behind (4), upstream colour/depth grads (4), T_final term, count.
        trans = np.zeros(TILE * TILE, np.float32)
        rest = np.zeros((TILE * TILE, 4), np.float32)
        up = np.zeros((TILE * TILE, 4), np.float32)
        g_final = np.zeros(TILE * TILE, np.float32)
        count = np.zeros(TILE * TILE, np.int32)
        k_end = 0
        for ly in range(tile_h):
            for lx in range(tile_w):
                p = ly * TILE + lx
                py = y0 + ly
                px = x0 + lx
                t_fin = final_t[py, px]
                gc0 = grad_color[py, px, 0]
                gc1 = grad_color[py, px, 1]
                gc2 = grad_color[py, px, 2]
                bg_grads[t, 0] += t_fin * gc0
                bg_grads[t, 1] += t_fin * gc1
                bg_grads[t, 2] += t_fin * gc2
                # d(loss)/d(alpha_k) through T_final (which scales the background and sets alpha)
                # is g_final / (1 - alpha_k).
                bg_dot = background[0] * gc0 + background[1] * gc1 + background[2] * gc2
                g_final[p] = t_fin * (grad_alpha[py, px] - bg_dot)
                trans[p] = t_fin
                up[p, 0] = gc0
                up[p, 1] = gc1
                up[p, 2] = gc2
                up[p, 3] = grad_depth[py, px]
                count[p] = n_contrib[py, px]
                k_end = max(k_end, count[p])
        for k in range(k_end - 1, -1, -1):
            if rects[k, 1] < rects[k, 0] or rects[k, 3] < rects[k, 2]:
                continue
            mx = feats[k, 0]
            my = feats[k, 1]
            ca = feats[k, 2]
            cb = feats[k, 3]
            cc = feats[k, 4]
            o = feats[k, 5]
            limit = feats[k, 6]
            idx = ids[start + k]
            col0 = colors[idx, 0]
            col1 = colors[idx, 1]
            col2 = colors[idx, 2]
            z = depths[idx]
            g_mx = _ZERO
            g_my = _ZERO
            g_a = _ZERO
            g_b = _ZERO
            g_c = _ZERO
            g_o = _ZERO
            g_c0 = _ZERO
            g_c1 = _ZERO
            g_c2 = _ZERO
            g_z = _ZERO
            for ly in range(rects[k, 2], rects[k, 3] + 1):
                dy = np.float32(y0 + ly) + _HALF - my
                for lx in range(rects[k, 0], rects[k, 1] + 1):
                    p = ly * TILE + lx
                    if k >= count[p]:
                        continue
                    dx = np.float32(x0 + lx) + _HALF - mx
                    power = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    if power > limit:
                        continue
                    gauss = np.exp(-power)
                    raw = o * gauss
                    alpha = min(_ALPHA_MAX, raw)
                    if alpha < _ALPHA_MIN:
                        continue
                    one_minus = _ONE - alpha
                    t_before = trans[p] / one_minus
                    trans[p] = t_before
                    w = alpha * t_before
                    u0 = up[p, 0]
                    u1 = up[p, 1]
                    u2 = up[p, 2]
                    ud = up[p, 3]
                    g_c0 += w * u0
                    g_c1 += w * u1
                    g_c2 += w * u2
                    g_z += w * ud
                    r0 = rest[p, 0]
                    r1 = rest[p, 1]
                    r2 = rest[p, 2]
                    rd = rest[p, 3]
                    g_alpha = t_before * ((col0 - r0) * u0 + (col1 - r1) * u1 + (col2 - r2) * u2
                                          + (z - rd) * ud) + g_final[p] / one_minus
                    rest[p, 0] = alpha * col0 + one_minus * r0
                    rest[p, 1] = alpha * col1 + one_minus * r1
                    rest[p, 2] = alpha * col2 + one_minus * r2
                    rest[p, 3] = alpha * z + one_minus * rd
                    if raw <= _ALPHA_MAX:
                        g_power = -alpha * g_alpha
                        g_o += gauss * g_alpha
                        g_mx -= g_power * (ca * dx + cb * dy)
                        g_my -= g_power * (cb * dx + cc * dy)
                        g_a += g_power * _HALF * dx * dx
                        g_b += g_power * dx * dy
                        g_c += g_power * _HALF * dy * dy
            row = start + k
            pair_grads[row, 0] = g_mx
            pair_grads[row, 1] = g_my
            pair_grads[row, 2] = g_a
            pair_grads[row, 3] = g_b
            pair_grads[row, 4] = g_c
            pair_grads[row, 5] = g_o
            pair_grads[row, 6] = g_c0
            pair_grads[row, 7] = g_c1
            pair_grads[row, 8] = g_c2
            pair_grads[row, 9] = g_z
    return pair_grads, bg_grads


@njit(parallel=True, cache=True)
def reduce_pairs(order, pair_start, pair_of, pair_grads, n):
    """Sum each Gaussian's per-tile gradients into (n, N_GRAD); one writer per Gaussian."""
    out = np.zeros((n, N_GRAD), np.float32)
    for k in prange(order.shape[0]):
        g = order[k]
        for p in range(pair_start[k], pair_start[k + 1]):
            row = pair_of[p]
            for j in range(N_GRAD):
                out[g, j] += pair_grads[row, j]
    return out
