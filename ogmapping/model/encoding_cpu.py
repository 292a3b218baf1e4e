"""Numba hash-grid encoding for the CPU, with a hand-written backward to the table's rows.

The torch encoding builds (anchors, levels, 8 corners, 3) integer and float tensors and runs some
fifteen ops over them each way; on two cores that was ~44 ms forward and most of a 100 ms backward
per 320x240 dense iteration. Here one parallel loop over the anchors hashes each level's eight
corners, interpolates the features in registers and keeps the rows and trilinear weights it used;
the backward is one multiply-add per lookup, summed in place into the same ``RowGradients`` sink as
the torch path's ``SparseRowGather`` deposits its pairs in (so ``LazyAdam`` steps both alike).
Anchor positions get no gradient.

The arithmetic follows ``HashGridEncoding.forward`` in float32 (cell coordinates, fractions and
weights), and the hash wraps int64 products as torch does, so the rows are identical and the
features agree to float32 rounding (tests/test_encoding_cpu.py).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ogmapping.arrays import float32_array
from ogmapping.model.row_gradients import RowGradients

_ONE = np.float32(1.0)


@njit(parallel=True, cache=True, error_model="numpy")
def _encode(points, resolutions, table, prime_y, prime_z, rows, weights, features):
    """features (M, L*F); rows (M, L, 8) flat table rows and weights (M, L, 8) of every lookup."""
    count = points.shape[0]
    levels, size, width = table.shape
    for m in prange(count):
        for level in range(levels):
            fx = points[m, 0] * resolutions[level]
            fy = points[m, 1] * resolutions[level]
            fz = points[m, 2] * resolutions[level]
            bx, by, bz = np.floor(fx), np.floor(fy), np.floor(fz)
            tx, ty, tz = fx - bx, fy - by, fz - bz
            ix, iy, iz = np.int64(bx), np.int64(by), np.int64(bz)
            for f in range(width):
                features[m, level * width + f] = 0.0
            for corner in range(8):
                cx, cy, cz = (corner >> 2) & 1, (corner >> 1) & 1, corner & 1
                hashed = (ix + cx) ^ ((iy + cy) * prime_y) ^ ((iz + cz) * prime_z)
                row = hashed % size
                weight = (tx if cx else _ONE - tx) * (ty if cy else _ONE - ty) * (tz if cz else _ONE - tz)
                rows[m, level, corner] = level * size + row
                weights[m, level, corner] = weight
                for f in range(width):
                    features[m, level * width + f] += weight * table[level, row, f]


class HashEncode(torch.autograd.Function):
    """``HashGridEncoding.forward`` as one kernel; the table's gradient rows go to ``sink``."""

    @staticmethod
    def forward(ctx, points: torch.Tensor, table: torch.Tensor, resolutions: torch.Tensor,
                primes: tuple[int, int, int], sink: RowGradients) -> torch.Tensor:
        """``primes``: the spatial hash's (1, p_y, p_z), as ``encoding.HASH_PRIMES``."""
        levels, _, width = table.shape
        count = points.shape[0]
        rows = np.empty((count, levels, 8), np.int64)
        weights = np.empty((count, levels, 8), np.float32)
        features = np.empty((count, levels * width), np.float32)
        _encode(float32_array(points), float32_array(resolutions), float32_array(table),
                np.int64(primes[1]), np.int64(primes[2]), rows, weights, features)
        ctx.lookups = (rows, weights)
        ctx.table_shape = table.shape
        ctx.sink = sink
        return torch.from_numpy(features)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[None, None, None, None, None]:
        rows, weights = ctx.lookups
        ctx.sink.accumulate_lookups(ctx.table_shape, rows, weights, float32_array(grad))
        return None, None, None, None, None
