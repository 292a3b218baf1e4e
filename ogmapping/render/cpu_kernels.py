"""Numba kernels of the cpu rasterizer: tile binning, front-to-back forward, back-to-front backward.

Layout: Gaussians are binned into 16x16 tiles (counting sort that keeps depth order); each tile
keeps its per-pixel state in flat float32 arrays and walks its list one Gaussian at a time over
the tile rows that Gaussian's ellipse spans. Those pixel loops are written branch-free (masks,
exact 0/1 arithmetic blends, a polynomial exp) so LLVM vectorises them with AVX2.

Exactness: all per-pixel arithmetic is float32 with float32 constants (a float64 literal would
silently promote the loops) and ``fastmath`` stays off, so the backward re-finds exactly the
contributors the forward composited. ``error_model="numpy"``: Python's would put a zero check
(an early exit) on every division and stop vectorisation.

Rules: ``rules.py``'s values are frozen into the compiled code, and Numba's on-disk cache
(``cache=True``) is checked against this file's timestamp only. After a change to ``rules.py``,
delete the cached kernels (``ogmapping/render/__pycache__/*.nb[ic]``), or they keep the old values
(the parity tests in ``tests/test_render_cpu.py`` then fail).

Threads: work is split by tile; every write goes to memory owned by the tile (its pixels, its
slice of the pair list) and per-Gaussian gradients are summed from per-pair buffers afterwards,
so the kernels are race-free and deterministic whatever the thread count.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from ogmapping.render.rules import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN

TILE = 16
# Gradient columns per Gaussian: mean x, mean y, conic a, b, c, opacity, colour r, g, b, depth.
N_GRAD = 10

_ALPHA_MIN = np.float32(ALPHA_MIN)
_ALPHA_MAX = np.float32(ALPHA_MAX)
_T_MIN = np.float32(TRANSMITTANCE_MIN)
_HALF = np.float32(0.5)
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)
# Added to the exact threshold log(opacity / ALPHA_MIN) on ``power`` beyond which a pixel is outside
# a Gaussian; far larger than float32 rounding, so it never rejects a pixel the alpha test keeps.
_POWER_SLACK = np.float32(1e-3)
# exp(-x) helper: arguments are clamped to [0, _EXP_CLAMP] (thresholds stay below 5.6 for
# opacities <= 1); Cody-Waite split of ln 2; exp(r) on [-ln2/2, ln2/2] by the degree-6 polynomial
# interpolating it at the Chebyshev nodes (error 2.5e-9, below float32 rounding).
_EXP_CLAMP = np.float32(10.0)
_LOG2E = np.float32(1.4426950408889634)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.1219444005469057e-4)
_P0 = np.float32(1.0)
_P1 = np.float32(1.0000000377)
_P2 = np.float32(0.50000000471)
_P3 = np.float32(0.16666415515)
_P4 = np.float32(0.041666352897)
_P5 = np.float32(0.0083751263981)
_P6 = np.float32(0.0013941108435)
# How often (in Gaussians) a tile rechecks which of its rows still have compositing pixels.
_OPEN_CHECK_EVERY = 8
# Tile-list entries the forward gathers at a time.
_GATHER_BLOCK = 64
# Tiles are stored as two half-tiles of this many columns (one AVX2 register of float32 per row).
_HALF_W = 8


@njit(inline="always", cache=True, error_model="numpy")
def _alpha_ellipse(a, b, c, o):
    """``limit`` and half-extents (ex, ey) of the ellipse ``power <= limit`` where a Gaussian of
    conic (a, b, c) and opacity ``o`` can reach ALPHA_MIN, padded by half a pixel; ex = ey = -1
    when the conic is degenerate (no bound beyond the radius) and ``limit <= 0`` means no pixel.

    The ellipse d^T conic d <= 2 limit spans sqrt(2 limit Sigma_ii) along each axis,
    Sigma = conic^-1 = [[c, -b], [-b, a]] / det.
    """
    limit = np.log(o / _ALPHA_MIN) + _POWER_SLACK
    det = np.float64(a) * np.float64(c) - np.float64(b) * np.float64(b)
    if det > 0.0 and limit > 0.0:
        ex = np.sqrt(2.0 * np.float64(limit) * np.float64(c) / det) + 0.5
        ey = np.sqrt(2.0 * np.float64(limit) * np.float64(a) / det) + 0.5
        return limit, ex, ey
    return limit, -1.0, -1.0


@njit(parallel=True, cache=True, error_model="numpy")
def bin_tiles(order, means2d, conics, opacities, radii, width, height, n_chunks):
    """Tile lists of the Gaussians ``order`` (visible ones, front to back) as CSR arrays.

    A Gaussian is listed in the tiles its bounding square (``radii``, the reference's rule) and
    the bounding box of its alpha ellipse (``_alpha_ellipse``, the bound ``_gather`` uses inside
    a tile) both reach: on 7-Scenes that is about half the square's tiles.

    Returns ``tile_offsets`` (n_tiles + 1), ``ids`` (pairs, Gaussian index per tile entry, each
    tile's slice front to back), ``pair_start``/``pair_of`` which map the k-th Gaussian of
    ``order`` to its entries, for the gradient reduction, and per Gaussian its ellipse
    (``limits``, ``extents``: ``_alpha_ellipse``), computed once here rather than once per tile
    entry by the forward and again by the backward. A counting sort over contiguous chunks of
    ``order`` keeps depth order inside every tile.
    """
    n = order.shape[0]
    limits = np.zeros(means2d.shape[0], np.float32)
    extents = np.full((means2d.shape[0], 2), -1.0)
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
        limit, ex, ey = _alpha_ellipse(conics[g, 0], conics[g, 1], conics[g, 2], opacities[g])
        limits[g] = limit
        extents[g, 0] = ex
        extents[g, 1] = ey
        if ex >= 0.0:
            # Pixel columns ceil(u - ex - 0.5) .. floor(u + ex - 0.5) (see ``_gather``), as tiles.
            x0 = max(x0, np.floor((u - ex - 0.5) / TILE))
            x1 = min(x1, np.floor((u + ex - 0.5) / TILE))
            y0 = max(y0, np.floor((v - ey - 0.5) / TILE))
            y1 = min(y1, np.floor((v + ey - 0.5) / TILE))
        if r > 0 and limit > 0.0 and x1 >= x0 and y1 >= y0:
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
    return tile_offsets, ids, pair_start, pair_of, limits, extents


@njit(inline="always", cache=True, error_model="numpy")
def _exp_neg(x):
    """exp(-x) for 0 <= x <= _EXP_CLAMP, within 2e-7 relative, in plain vectorisable arithmetic.

    libm's expf is an opaque call that stops LLVM from vectorising the pixel loops. Here
    exp(-x) = 2^-n exp(r) with r = n ln2 - x in [-ln2/2, ln2/2] (ln2 split so n * _LN2_HI is
    exact), exp(r) from a degree-6 polynomial evaluated in Estrin's scheme (short dependency
    chain), and 2^-n assembled from the bits of n.
    """
    n = np.int32(x * _LOG2E + _HALF)
    nf = np.float32(n)
    r = (nf * _LN2_HI - x) + nf * _LN2_LO
    r2 = r * r
    p = (_P0 + _P1 * r) + r2 * ((_P2 + _P3 * r) + r2 * ((_P4 + _P5 * r) + r2 * _P6))
    s1 = np.float32(0.5) if (n & 1) != 0 else _ONE
    s2 = np.float32(0.25) if (n & 2) != 0 else _ONE
    s4 = np.float32(0.0625) if (n & 4) != 0 else _ONE
    s8 = np.float32(0.00390625) if (n & 8) != 0 else _ONE
    return p * ((s1 * s2) * (s4 * s8))


@njit(cache=True, error_model="numpy")
def _gather(
    ids, start, k0, k1, means2d, conics, opacities, colors, depths, limits, extents, x0, y0, tile_w, tile_h,
    feats, spans,
):
    """Copy entries [k0, k1) of one tile's list (front to back) into contiguous rows.

    Row k of ``feats``: mean x, mean y, conic a, b, c, opacity, power threshold, colour r, g, b,
    depth. ``spans[k]`` holds the inclusive range of tile rows and of half-tiles (columns
    [0, _HALF_W) and [_HALF_W, TILE)) whose pixel centres can lie within the ellipse
    ``power <= threshold``: its bounding box, padded by half a pixel. Empty ranges have end < start.
    """
    for k in range(k0, k1):
        idx = ids[start + k]
        o = opacities[idx]
        a = conics[idx, 0]
        b = conics[idx, 1]
        c = conics[idx, 2]
        limit = limits[idx]
        ex = extents[idx, 0]
        ey = extents[idx, 1]
        feats[k, 0] = means2d[idx, 0]
        feats[k, 1] = means2d[idx, 1]
        feats[k, 2] = a
        feats[k, 3] = b
        feats[k, 4] = c
        feats[k, 5] = o
        feats[k, 6] = limit
        feats[k, 7] = colors[idx, 0]
        feats[k, 8] = colors[idx, 1]
        feats[k, 9] = colors[idx, 2]
        feats[k, 10] = depths[idx]
        lo_y, hi_y, lo_x, hi_x = 0, tile_h - 1, 0, tile_w - 1
        if ex >= 0.0:
            mx = np.float64(means2d[idx, 0])
            my = np.float64(means2d[idx, 1])
            lo_x = max(lo_x, np.int64(max(np.ceil(mx - ex - 0.5) - x0, -1.0)))
            hi_x = min(hi_x, np.int64(min(np.floor(mx + ex - 0.5) - x0, tile_w + 0.0)))
            lo_y = max(lo_y, np.int64(max(np.ceil(my - ey - 0.5) - y0, -1.0)))
            hi_y = min(hi_y, np.int64(min(np.floor(my + ey - 0.5) - y0, tile_h + 0.0)))
        elif limit <= 0.0:
            hi_y = -1
        spans[k, 0] = lo_y
        spans[k, 1] = hi_y
        spans[k, 2] = lo_x // _HALF_W
        spans[k, 3] = hi_x // _HALF_W if hi_x >= lo_x else -1


@njit(inline="always", cache=True, error_model="numpy")
def _forward_run(p0, n, xs, ys, f, k_next, st, last):
    """Composite Gaussian ``f`` over the ``n`` tile pixels from flat index ``p0``.

    ``st`` (5, TILE^2) holds transmittance and colour/depth sums, ``last`` the list length
    composited so far. A pixel that has stopped keeps its transmittance negated. Branch-free with
    unsigned indices (no negative-index wraparound) so LLVM vectorises it, and every state update
    is an exact arithmetic blend with m in {0, 1}: a "x if c else old" store would become a masked
    store, which is very slow on some CPUs (AMD Zen).
    """
    mx, my, ca, cb, cc, o, limit = f[0], f[1], f[2], f[3], f[4], f[5], f[6]
    c0, c1, c2, z = f[7], f[8], f[9], f[10]
    base = np.uint64(p0)
    for j in range(n):
        p = base + np.uint64(j)
        dx = xs[p] - mx
        dy = ys[p] - my
        power = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
        alpha = min(_ALPHA_MAX, o * _exp_neg(min(max(power, _ZERO), _EXP_CLAMP)))
        t = st[0, p]
        next_t = t * (_ONE - alpha)
        hit = (power <= limit) & (alpha >= _ALPHA_MIN) & (t > _ZERO)
        m = _ONE if (hit & (next_t >= _T_MIN)) else _ZERO
        stop = _ONE if (hit & (next_t < _T_MIN)) else _ZERO
        w = alpha * t * m
        st[0, p] = next_t * m - t * stop + t * (_ONE - m - stop)
        st[1, p] += w * c0
        st[2, p] += w * c1
        st[3, p] += w * c2
        st[4, p] += w * z
        mi = np.int32(m)
        last[p] = k_next * mi + last[p] * (np.int32(1) - mi)


@njit(inline="always", cache=True, error_model="numpy")
def _refresh_open_rows(st, open_rows):
    """Mark half-tile rows with a pixel still compositing; returns whether any is open."""
    any_open = False
    for h in range(2):
        for ly in range(TILE):
            row_open = False
            for j in range(_HALF_W):
                if st[0, _pixel(h, ly, j)] > _ZERO:
                    row_open = True
                    break
            open_rows[h, ly] = row_open
            any_open = any_open or row_open
    return any_open


@njit(inline="always", cache=True, error_model="numpy")
def _pixel(h, ly, j):
    """Flat index of tile pixel (row ly, column h * _HALF_W + j): half-tiles are stored one after
    the other, row-major, so consecutive rows of one half form a contiguous run."""
    return h * (_HALF_W * TILE) + ly * _HALF_W + j


@njit(inline="always", cache=True, error_model="numpy")
def _pixel_centres(x0, y0):
    """Pixel-centre x and y coordinates of a tile in the flat layout of ``_pixel``."""
    xs = np.empty(TILE * TILE, np.float32)
    ys = np.empty(TILE * TILE, np.float32)
    for h in range(2):
        for ly in range(TILE):
            for j in range(_HALF_W):
                xs[_pixel(h, ly, j)] = np.float32(x0 + h * _HALF_W + j) + _HALF
                ys[_pixel(h, ly, j)] = np.float32(y0 + ly) + _HALF
    return xs, ys


@njit(cache=True, error_model="numpy")
def _forward_tile(
    t, n_x, tile_offsets, ids, means2d, conics, opacities, colors, depths, limits, extents, background, width, height,
    out_color, out_depth, out_t, n_contrib,
):
    """Forward of one tile: Gaussians front to back, each over the half-tile rows it can reach.

    Half-tile rows whose pixels have all stopped are skipped (rechecked every _OPEN_CHECK_EVERY
    Gaussians) and the tile ends when none is left; per pixel, order and rules are the reference's.
    """
    ty = t // n_x
    x0 = (t - ty * n_x) * TILE
    y0 = ty * TILE
    tile_w = min(TILE, width - x0)
    tile_h = min(TILE, height - y0)
    start = tile_offsets[t]
    g = tile_offsets[t + 1] - start
    # Gathered in blocks as compositing advances: most tiles saturate long before their list ends.
    feats = np.empty((g, 11), np.float32)
    spans = np.empty((g, 4), np.int64)
    gathered = 0
    xs, ys = _pixel_centres(x0, y0)
    st = np.zeros((5, TILE * TILE), np.float32)
    st[0] = -_ONE  # pixels outside the image start (and stay) stopped
    for ly in range(tile_h):
        for lx in range(tile_w):
            st[0, _pixel(lx // _HALF_W, ly, lx % _HALF_W)] = _ONE
    last = np.zeros(TILE * TILE, np.int32)
    open_rows = np.ones((2, TILE), np.bool_)
    for k in range(g):
        if k % _OPEN_CHECK_EVERY == 0 and not _refresh_open_rows(st, open_rows):
            break
        if k == gathered:
            gathered = min(g, gathered + _GATHER_BLOCK)
            _gather(
                ids, start, k, gathered, means2d, conics, opacities, colors, depths, limits, extents, x0, y0,
                tile_w, tile_h, feats, spans,
            )
        f = feats[k]
        for h in range(spans[k, 2], spans[k, 3] + 1):
            ly = spans[k, 0]
            while ly <= spans[k, 1]:
                if not open_rows[h, ly]:
                    ly += 1
                    continue
                first = ly
                while ly <= spans[k, 1] and open_rows[h, ly]:
                    ly += 1
                _forward_run(_pixel(h, first, 0), (ly - first) * _HALF_W, xs, ys, f, np.int32(k + 1), st, last)
    for ly in range(tile_h):
        for lx in range(tile_w):
            p = _pixel(lx // _HALF_W, ly, lx % _HALF_W)
            py = y0 + ly
            px = x0 + lx
            t_end = abs(st[0, p])
            out_color[py, px, 0] = st[1, p] + t_end * background[0]
            out_color[py, px, 1] = st[2, p] + t_end * background[1]
            out_color[py, px, 2] = st[3, p] + t_end * background[2]
            out_depth[py, px] = st[4, p]
            out_t[py, px] = t_end
            n_contrib[py, px] = last[p]


@njit(cache=True, error_model="numpy")
def _balanced_schedule(tile_offsets, n_threads):
    """Tile order whose equal contiguous chunks (prange's static split) carry similar work.

    Tiles sorted by list length, the cost proxy, are dealt to the chunks in a snake pattern so
    every thread gets a share of the busiest tiles, whatever the scene's layout on screen.
    """
    n_tiles = tile_offsets.shape[0] - 1
    by_cost = np.argsort(-(tile_offsets[1:] - tile_offsets[:-1]), kind="mergesort")
    bounds = np.empty(n_threads + 1, np.int64)
    for c in range(n_threads + 1):
        bounds[c] = c * n_tiles // n_threads
    fill = bounds[:-1].copy()
    schedule = np.empty(n_tiles, np.int64)
    c, step = 0, 1
    for t in by_cost:
        while fill[c] == bounds[c + 1]:
            c, step = _next_chunk(c, step, n_threads)
        schedule[fill[c]] = t
        fill[c] += 1
        c, step = _next_chunk(c, step, n_threads)
    return schedule


@njit(inline="always", cache=True, error_model="numpy")
def _next_chunk(c, step, n_chunks):
    """Next chunk of a snake walk 0, 1, .., n-1, n-1, .., 0, 0, 1, .."""
    if 0 <= c + step < n_chunks:
        return c + step, step
    return c, -step


@njit(parallel=True, cache=True, error_model="numpy")
def render_forward(
    tile_offsets, ids, means2d, conics, opacities, colors, depths, limits, extents, background, width, height, n_threads
):
    """Composite every pixel front to back, one tile per task.

    Returns colour over ``background`` (H, W, 3), accumulated depth (H, W), final transmittance
    (H, W) and, per pixel, the length of the tile-list prefix the backward has to revisit.
    """
    n_x = (width + TILE - 1) // TILE
    n_tiles = n_x * ((height + TILE - 1) // TILE)
    out_color = np.empty((height, width, 3), np.float32)
    out_depth = np.empty((height, width), np.float32)
    out_t = np.empty((height, width), np.float32)
    n_contrib = np.empty((height, width), np.int32)
    schedule = _balanced_schedule(tile_offsets, n_threads)
    for i in prange(n_tiles):
        _forward_tile(
            schedule[i], n_x, tile_offsets, ids, means2d, conics, opacities, colors, depths, limits, extents,
            background, width, height, out_color, out_depth, out_t, n_contrib,
        )
    return out_color, out_depth, out_t, n_contrib


@njit(inline="always", cache=True, error_model="numpy")
def _row_major_centres(x0, y0):
    """Pixel-centre x and y coordinates of a tile, flat and row-major (the backward's layout)."""
    xs = np.empty(TILE * TILE, np.float32)
    ys = np.empty(TILE * TILE, np.float32)
    for ly in range(TILE):
        for lx in range(TILE):
            xs[ly * TILE + lx] = np.float32(x0 + lx) + _HALF
            ys[ly * TILE + lx] = np.float32(y0 + ly) + _HALF
    return xs, ys


@njit(inline="always", cache=True, error_model="numpy")
def _backward_run(p0, lane0, lane1, n, xs, ys, f, k, count, st, lanes):
    """Undo Gaussian ``f`` over columns [lane0, lane1) of the ``n``-pixel tile row at flat index ``p0``.

    ``st`` (10, TILE^2) holds per pixel the transmittance, colour/depth behind (4), upstream
    colour/depth gradients (4) and the T_final term; the pixels' gradient terms are added to
    ``lanes`` (N_GRAD, TILE), one lane per column, which the caller sums. Branch-free and with
    exact arithmetic blends, like ``_forward_run``, so LLVM vectorises it.

    The loop always spans the whole row and masks off the columns outside [lane0, lane1) (for
    them every update adds zero): a row of 16 float32 is one pass of LLVM's AVX-512 loop, where a
    half row (half of the runs on 7-Scenes) fell to its 4-wide remainder loop; 25% faster.
    """
    mx, my, ca, cb, cc, o, limit = f[0], f[1], f[2], f[3], f[4], f[5], f[6]
    c0, c1, c2, z = f[7], f[8], f[9], f[10]
    base = np.uint64(p0)
    for j in range(n):
        p = base + np.uint64(j)
        q = np.uint64(j)
        dx = xs[p] - mx
        dy = ys[p] - my
        power = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
        gauss = _exp_neg(min(max(power, _ZERO), _EXP_CLAMP))
        raw = o * gauss
        alpha = min(_ALPHA_MAX, raw)
        active = (k < count[p]) & (power <= limit) & (alpha >= _ALPHA_MIN) & (q >= lane0) & (q < lane1)
        one_minus = _ONE - alpha
        inv_one_minus = _ONE / one_minus
        t_after = st[0, p]
        t_before = t_after * inv_one_minus
        r0 = st[1, p]
        r1 = st[2, p]
        r2 = st[3, p]
        rd = st[4, p]
        u0 = st[5, p]
        u1 = st[6, p]
        u2 = st[7, p]
        ud = st[8, p]
        w = alpha * t_before if active else _ZERO
        lanes[6, q] += w * u0
        lanes[7, q] += w * u1
        lanes[8, q] += w * u2
        lanes[9, q] += w * ud
        g_alpha = t_before * ((c0 - r0) * u0 + (c1 - r1) * u1 + (c2 - r2) * u2 + (z - rd) * ud) + (
            st[9, p] * inv_one_minus
        )
        differentiable = active & (raw <= _ALPHA_MAX)
        g_power = -alpha * g_alpha if differentiable else _ZERO
        lanes[0, q] -= g_power * (ca * dx + cb * dy)
        lanes[1, q] -= g_power * (cb * dx + cc * dy)
        lanes[2, q] += g_power * _HALF * dx * dx
        lanes[3, q] += g_power * dx * dy
        lanes[4, q] += g_power * _HALF * dy * dy
        lanes[5, q] += gauss * g_alpha if differentiable else _ZERO
        m = _ONE if active else _ZERO
        keep = _ONE - m
        st[0, p] = t_before * m + t_after * keep
        st[1, p] = (alpha * c0 + one_minus * r0) * m + r0 * keep
        st[2, p] = (alpha * c1 + one_minus * r1) * m + r1 * keep
        st[3, p] = (alpha * c2 + one_minus * r2) * m + r2 * keep
        st[4, p] = (alpha * z + one_minus * rd) * m + rd * keep


@njit(inline="always", cache=True, error_model="numpy")
def _halves_in_reach(p0, n, xs, ys, f, k, count):
    """Whether columns [0, _HALF_W) and [_HALF_W, n) of a row hold a pixel that Gaussian ``f``
    (list entry ``k``) can reach: inside its threshold ellipse and not yet past its stop."""
    mx, my, ca, cb, cc, limit = f[0], f[1], f[2], f[3], f[4], f[6]
    base = np.uint64(p0)
    left = 0
    right = 0
    for j in range(n):
        p = base + np.uint64(j)
        dx = xs[p] - mx
        dy = ys[p] - my
        power = _HALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
        reach = 1 if ((k < count[p]) & (power <= limit)) else 0
        if j < _HALF_W:
            left |= reach
        else:
            right |= reach
    return left != 0, right != 0


@njit(inline="always", cache=True, error_model="numpy")
def _sum_lanes(v):
    """Sum of the TILE (16) lanes of ``v`` as a balanced tree: four dependent adds instead of a
    16-long chain, for ten gradient columns per tile entry."""
    q0 = (v[0] + v[1]) + (v[2] + v[3])
    q1 = (v[4] + v[5]) + (v[6] + v[7])
    q2 = (v[8] + v[9]) + (v[10] + v[11])
    q3 = (v[12] + v[13]) + (v[14] + v[15])
    return (q0 + q1) + (q2 + q3)


@njit(cache=True, error_model="numpy")
def _backward_tile(
    t, n_x, tile_offsets, ids, means2d, conics, opacities, colors, depths, limits, extents, background,
    final_t, n_contrib, grad_color, grad_depth, grad_alpha, width, height, pair_grads, bg_grads,
):
    """Backward of one tile: Gaussians back to front over the rows they span, as in the forward.

    Per pixel state is row-major here (16-lane rows vectorise best for this heavier loop). A
    Gaussian is visited on the forward's half-tile rows (``_gather`` spans) minus those where no
    pixel can have used it, and pixels apply the forward's float32 test, so the backward re-finds
    precisely the forward's contributors.
    """
    ty = t // n_x
    x0 = (t - ty * n_x) * TILE
    y0 = ty * TILE
    tile_w = min(TILE, width - x0)
    tile_h = min(TILE, height - y0)
    start = tile_offsets[t]
    xs, ys = _row_major_centres(x0, y0)
    st = np.zeros((10, TILE * TILE), np.float32)
    count = np.zeros(TILE * TILE, np.int32)
    row_count = np.zeros(TILE, np.int64)
    lanes = np.zeros((N_GRAD, TILE), np.float32)
    bg0 = _ZERO
    bg1 = _ZERO
    bg2 = _ZERO
    for ly in range(tile_h):
        for lx in range(tile_w):
            p = ly * TILE + lx
            py = y0 + ly
            px = x0 + lx
            t_end = final_t[py, px]
            gc0 = grad_color[py, px, 0]
            gc1 = grad_color[py, px, 1]
            gc2 = grad_color[py, px, 2]
            bg0 += t_end * gc0
            bg1 += t_end * gc1
            bg2 += t_end * gc2
            st[0, p] = t_end
            st[5, p] = gc0
            st[6, p] = gc1
            st[7, p] = gc2
            st[8, p] = grad_depth[py, px]
            # d(loss)/d(alpha_k) through T_final (which scales the background and sets the
            # alpha output) is this term over (1 - alpha_k).
            bg_dot = background[0] * gc0 + background[1] * gc1 + background[2] * gc2
            st[9, p] = t_end * (grad_alpha[py, px] - bg_dot)
            count[p] = n_contrib[py, px]
            row_count[ly] = max(row_count[ly], n_contrib[py, px])
    # Written once: neighbouring tiles' rows share cache lines and may run on other threads.
    bg_grads[t, 0] = bg0
    bg_grads[t, 1] = bg1
    bg_grads[t, 2] = bg2
    k_end = 0
    for ly in range(tile_h):
        k_end = max(k_end, row_count[ly])
    feats = np.empty((k_end, 11), np.float32)
    spans = np.empty((k_end, 4), np.int64)
    _gather(
        ids, start, 0, k_end, means2d, conics, opacities, colors, depths, limits, extents, x0, y0, tile_w, tile_h,
        feats, spans,
    )
    for k in range(k_end - 1, -1, -1):
        f = feats[k]
        touched = False
        for ly in range(spans[k, 0], spans[k, 1] + 1):
            if k >= row_count[ly]:
                continue
            # Halves of the row (columns [0, 8) and [8, tile_w)) that the forward visited for this
            # Gaussian and where some pixel may be active; the test is the run's own float32
            # test, so skipping a half never drops a contributor.
            p0 = ly * TILE
            left, right = _halves_in_reach(p0, tile_w, xs, ys, f, np.int32(k), count)
            left = left and spans[k, 2] <= 0 <= spans[k, 3]
            right = right and spans[k, 2] <= 1 <= spans[k, 3]
            if left or right:
                lane0 = 0 if left else _HALF_W
                lane1 = tile_w if right else min(_HALF_W, tile_w)
                _backward_run(p0, np.uint64(lane0), np.uint64(lane1), tile_w, xs, ys, f, np.int32(k), count, st, lanes)
                touched = True
        if touched:
            row = start + k
            for j in range(N_GRAD):
                pair_grads[row, j] = _sum_lanes(lanes[j])
            lanes[:] = _ZERO


@njit(parallel=True, cache=True, error_model="numpy")
def render_backward(
    tile_offsets, ids, means2d, conics, opacities, colors, depths, limits, extents, background,
    final_t, n_contrib, grad_color, grad_depth, grad_alpha, width, height, n_threads,
):
    """Gradients per tile entry (pairs, N_GRAD) and per tile for the background (n_tiles, 3).

    Walks each tile's Gaussians back to front; every pixel recovers the transmittance before each
    contributor as ``T / (1 - alpha)`` and keeps the colour and depth composited behind it as
    running sums. A Gaussian's gradient is summed over per-lane partial sums and written once,
    to its own tile entry, so tiles never write to shared memory.
    """
    n_x = (width + TILE - 1) // TILE
    n_tiles = n_x * ((height + TILE - 1) // TILE)
    pair_grads = np.zeros((tile_offsets[n_tiles], N_GRAD), np.float32)
    bg_grads = np.zeros((n_tiles, 3), np.float32)
    schedule = _balanced_schedule(tile_offsets, n_threads)
    for i in prange(n_tiles):
        _backward_tile(
            schedule[i], n_x, tile_offsets, ids, means2d, conics, opacities, colors, depths, limits, extents,
            background, final_t, n_contrib, grad_color, grad_depth, grad_alpha, width, height, pair_grads, bg_grads,
        )
    return pair_grads, bg_grads


@njit(parallel=True, cache=True, error_model="numpy")
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
