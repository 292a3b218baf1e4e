"""The Numba SSIM blur: a zero-padded separable filter per channel, summed tap by tap in order."""

from __future__ import annotations

import numpy as np
import pytest

from ogmapping.optim.blur import blur
from ogmapping.optim.ssim import _TAPS_64, TAPS


def _tap_by_tap(maps: np.ndarray, taps: np.ndarray, channels: int) -> np.ndarray:
    """The filter as numpy sums over zero-padded shifts, each from zero and in tap order."""
    radius = len(taps) // 2
    count, height, length = maps.shape
    padded = np.zeros((count, height + 2 * radius, length), maps.dtype)
    padded[:, radius:radius + height] = maps
    column = np.zeros((count, height, length + 2 * radius * channels), maps.dtype)
    for k, tap in enumerate(taps):
        column[:, :, radius * channels:radius * channels + length] += tap * padded[:, k:k + height]
    out = np.zeros_like(maps)
    for k, tap in enumerate(taps):
        out += tap * column[:, :, k * channels:k * channels + length]
    return out


@pytest.mark.parametrize("dtype, taps", [(np.float32, TAPS), (np.float64, _TAPS_64)], ids=["float32", "float64"])
@pytest.mark.parametrize("shape", [(3, 37, 53), (2, 4, 7), (1, 1, 9)], ids=["image", "fewer rows than taps", "one row"])
def test_blur_is_the_zero_padded_filter_to_the_bit(dtype, taps, shape):
    count, height, width = shape
    maps = np.random.default_rng(0).standard_normal((count, height, width * 3)).astype(dtype)
    maps[0, :, :6] = 0.0
    assert np.array_equal(blur(maps, taps, 3), _tap_by_tap(maps, taps, 3))


def test_blur_keeps_channels_apart():
    """A single lit pixel of one channel spreads into that channel only, as the window's outer product."""
    maps = np.zeros((1, 21, 21 * 3), np.float64)
    maps[0, 10, 10 * 3 + 1] = 1.0
    out = blur(maps, _TAPS_64, 3).reshape(21, 21, 3)
    assert not out[..., 0].any() and not out[..., 2].any()
    np.testing.assert_allclose(out[5:16, 5:16, 1], np.outer(_TAPS_64, _TAPS_64), rtol=1e-12)


def test_blur_refuses_another_window():
    with pytest.raises(ValueError, match="11 taps"):
        blur(np.zeros((1, 4, 12), np.float32), TAPS[:9].copy(), 3)
