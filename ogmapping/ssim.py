"""Differentiable SSIM, shared by the training loss and the evaluation metric.

One implementation for both keeps "what we optimise" and "what we report" the same quantity:
an 11x11 Gaussian window (sigma 1.5) applied as two separable 1-D convolutions, with the usual
constants for images in [0, 1]. Borders use zero padding ("same" size output); the metric drops
a border afterwards, the loss simply averages the whole map.
"""

from __future__ import annotations

from dataclasses import dataclass

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


@dataclass
class ReferenceStatistics:
    """The blurred mean and second moment of a fixed image, computed once per keyframe.

    The ground-truth side of SSIM never changes during mapping, so caching it saves two of the
    five blurs of every loss evaluation. All three are (H, W, C), like the image they describe.
    """

    image: torch.Tensor
    mean: torch.Tensor
    square_mean: torch.Tensor


def _nchw(image: torch.Tensor) -> torch.Tensor:
    return image.permute(2, 0, 1)[None]


def _hwc(batch: torch.Tensor) -> torch.Tensor:
    return batch[0].permute(1, 2, 0).contiguous()


def reference_statistics(b: torch.Tensor) -> ReferenceStatistics:
    """Statistics of an (H, W, C) image for repeated ``ssim_map`` calls against it."""
    y = _nchw(b).contiguous()
    taps = gaussian_window(dtype=y.dtype, device=y.device)
    return ReferenceStatistics(image=b, mean=_hwc(_blur(y, taps)), square_mean=_hwc(_blur(y * y, taps)))


def ssim_map(a: torch.Tensor, b: torch.Tensor, reference: ReferenceStatistics | None = None) -> torch.Tensor:
    """Per-pixel, per-channel SSIM of two (H, W, C) images in [0, 1]; returns (H, W, C).

    ``reference``, when given, must be ``reference_statistics(b)``.
    """
    if a.shape != b.shape or a.dim() != 3:
        raise ValueError(f"ssim_map expects two (H, W, C) images of one shape, got {a.shape} and {b.shape}")
    reference = reference if reference is not None else reference_statistics(b)
    x = _nchw(a)
    y = _nchw(reference.image)
    taps = gaussian_window(dtype=x.dtype, device=x.device)
    mu_x, mu_y = _blur(x, taps), _nchw(reference.mean)
    var_x = _blur(x * x, taps) - mu_x**2
    var_y = _nchw(reference.square_mean) - mu_y**2
    cov = _blur(x * y, taps) - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + C1) * (2 * cov + C2)
    denominator = (mu_x**2 + mu_y**2 + C1) * (var_x + var_y + C2)
    return _hwc(numerator / denominator)
