"""Differentiable SSIM, shared by the training loss and the evaluation metric.

One implementation for both keeps "what we optimise" and "what we report" the same quantity:
an 11x11 Gaussian window (sigma 1.5) applied as two separable 1-D convolutions, with the usual
constants for images in [0, 1]. Borders use zero padding ("same" size output); the metric drops
a border afterwards, the loss simply averages the whole map.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

WINDOW_SIZE = 11
SIGMA = 1.5
C1 = 0.01**2
C2 = 0.03**2


def gaussian_window(
    size: int = WINDOW_SIZE,
    sigma: float = SIGMA,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """Normalised 1-D Gaussian taps of length ``size``."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    taps = torch.exp(-(x**2) / (2 * sigma**2))
    return taps / taps.sum()


def _blur(x: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of a (B, C, H, W) tensor, each channel on its own."""
    channels = x.shape[1]
    pad = taps.numel() // 2
    horizontal = taps.view(1, 1, 1, -1).expand(channels, 1, 1, -1)
    vertical = taps.view(1, 1, -1, 1).expand(channels, 1, -1, 1)
    x = F.conv2d(x, horizontal, padding=(0, pad), groups=channels)
    return F.conv2d(x, vertical, padding=(pad, 0), groups=channels)


def ssim_map(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-pixel, per-channel SSIM of two (H, W, C) images in [0, 1]; returns (H, W, C)."""
    if a.shape != b.shape or a.dim() != 3:
        raise ValueError(f"ssim_map expects two (H, W, C) images of one shape, got {a.shape} and {b.shape}")
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    taps = gaussian_window(dtype=x.dtype, device=x.device)
    mu_x, mu_y = _blur(x, taps), _blur(y, taps)
    var_x = _blur(x * x, taps) - mu_x**2
    var_y = _blur(y * y, taps) - mu_y**2
    cov = _blur(x * y, taps) - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + C1) * (2 * cov + C2)
    denominator = (mu_x**2 + mu_y**2 + C1) * (var_x + var_y + C2)
    return (numerator / denominator)[0].permute(1, 2, 0)
