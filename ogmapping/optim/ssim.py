"""Differentiable SSIM, shared by the training loss and the evaluation metric.

One implementation for both keeps "what we optimise" and "what we report" the same quantity:
an 11x11 Gaussian window (sigma 1.5) applied as two separable 1-D convolutions, with the usual
constants for images in [0, 1]. Borders use zero padding ("same" size output); the metric drops
a border afterwards, the loss simply averages the whole map. With ``compiled`` (the caller's
choice: CPU images, nothing needing a gradient, e.g. the metric or keyframes' cached statistics
in a compiled execution profile) the blurs run in the Numba kernel of ``ogmapping.optim.blur``: the
same window and padding, ~10x faster than torch's grouped convolutions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ogmapping.arrays import image_planes
from ogmapping.optim.blur import blur

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


TAPS = gaussian_window().numpy()  # float32 taps for the Numba blur
_TAPS_64 = gaussian_window(dtype=torch.float64).numpy()


def _blur_hwc(*images: torch.Tensor) -> list[torch.Tensor]:
    """Numba blur of (H, W, C) CPU images of one shape and dtype (float32 or float64), each channel
    on its own; the Numba blur has no backward, so asking for a gradient is an error."""
    if torch.is_grad_enabled() and any(t.requires_grad for t in images):
        raise ValueError("the compiled SSIM blur has no gradient; pass compiled=False where one is needed")
    height, width, channels = images[0].shape
    planes = np.stack([image_planes(t, t.dtype) for t in images])
    taps = _TAPS_64 if planes.dtype == np.float64 else TAPS
    blurred = torch.from_numpy(blur(planes, taps, channels))
    return [plane.view(height, width, channels) for plane in blurred]


def _blur(x: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of a (B, C, H, W) tensor, each channel on its own."""
    channels = x.shape[1]
    pad = taps.numel() // 2
    if torch.compiler.is_compiling():
        return _shifted_sums(_shifted_sums(x, taps, 3), taps, 2)
    horizontal = taps.view(1, 1, 1, -1).expand(channels, 1, 1, -1)
    vertical = taps.view(1, 1, -1, 1).expand(channels, 1, -1, 1)
    x = F.conv2d(x, horizontal, padding=(0, pad), groups=channels)
    return F.conv2d(x, vertical, padding=(pad, 0), groups=channels)


def _shifted_sums(x: torch.Tensor, taps: torch.Tensor, dim: int) -> torch.Tensor:
    """The 1-D blur along ``dim`` as a sum of the zero-padded image shifted by each tap: in a compiled
    graph it fuses into one kernel with what surrounds it, where a convolution stays a call of its own."""
    pad = taps.numel() // 2
    size = x.shape[dim]
    padding = [0, 0] * (x.dim() - 1 - dim) + [pad, pad]
    padded = F.pad(x, padding)
    return sum(taps[k] * padded.narrow(dim, k, size) for k in range(taps.numel()))


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


def reference_statistics(b: torch.Tensor, *, compiled: bool) -> ReferenceStatistics:
    """Statistics of an (H, W, C) image for repeated ``ssim_map`` calls against it; ``compiled``
    blurs it in Numba (a CPU image)."""
    if compiled:
        mean, square_mean = _blur_hwc(b, b * b)
        return ReferenceStatistics(image=b, mean=mean, square_mean=square_mean)
    y = _nchw(b).contiguous()
    taps = gaussian_window(dtype=y.dtype, device=y.device)
    return ReferenceStatistics(image=b, mean=_hwc(_blur(y, taps)), square_mean=_hwc(_blur(y * y, taps)))


def ssim_map(a: torch.Tensor, b: torch.Tensor, reference: ReferenceStatistics | None = None, *,
             compiled: bool) -> torch.Tensor:
    """Per-pixel, per-channel SSIM of two (H, W, C) images in [0, 1]; returns (H, W, C).

    ``reference``, when given, must be ``reference_statistics(b)`` (blurred either way).
    ``compiled`` blurs in Numba: CPU images of one dtype, no gradient; otherwise in torch,
    differentiable, on any device.
    """
    if a.shape != b.shape or a.dim() != 3:
        raise ValueError(f"ssim_map expects two (H, W, C) images of one shape, got {a.shape} and {b.shape}")
    reference = reference if reference is not None else reference_statistics(b, compiled=compiled)
    if compiled:
        x, y = a, reference.image
        mu_x, square_mean_x, mean_xy = _blur_hwc(x, x * x, x * y)
        mu_y, square_mean_y = reference.mean, reference.square_mean
    else:
        x, y = _nchw(a), _nchw(reference.image)
        taps = gaussian_window(dtype=x.dtype, device=x.device)
        mu_x, mu_y = _blur(x, taps), _nchw(reference.mean)
        square_mean_x, square_mean_y, mean_xy = _blur(x * x, taps), _nchw(reference.square_mean), _blur(x * y, taps)
    var_x = square_mean_x - mu_x**2
    var_y = square_mean_y - mu_y**2
    cov = mean_xy - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + C1) * (2 * cov + C2)
    denominator = (mu_x**2 + mu_y**2 + C1) * (var_x + var_y + C2)
    ssim = numerator / denominator
    return ssim if ssim.dim() == 3 else _hwc(ssim)
