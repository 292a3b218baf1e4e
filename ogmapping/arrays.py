"""Tensors as C-contiguous numpy arrays for the compiled (Numba) kernels: the one conversion.

Every compiled op (rasterizer, Gaussian assembly, hash encoding, fused loss, SSIM blur) hands its
kernels detached, C-contiguous CPU arrays of one dtype, so each kernel compiles one signature
whatever layout or dtype the caller's tensor had; a tensor that already is one becomes a view,
not a copy.
"""

from __future__ import annotations

import numpy as np
import torch


def float32_array(t: torch.Tensor) -> np.ndarray:
    """``t`` as a C-contiguous float32 array on the CPU (no gradient)."""
    return _contiguous(t, torch.float32)


def image_planes(image: torch.Tensor, dtype: torch.dtype = torch.float32) -> np.ndarray:
    """An (H, W, C) image as the C-contiguous (H, W * C) array the image kernels take."""
    return _contiguous(image, dtype).reshape(image.shape[0], -1)


def _contiguous(t: torch.Tensor, dtype: torch.dtype) -> np.ndarray:
    if t.requires_grad:  # detached only then: each operator is a dispatch, and a step converts dozens of tensors
        t = t.detach()
    return np.ascontiguousarray(t.to("cpu", dtype).numpy())
