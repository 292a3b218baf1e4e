"""Module-level constant tensors, copied to each device and dtype once instead of at every call.

On CUDA, ``CONSTANT.to(device)`` inside the mapping loop is a host-to-device copy, and with it a
host synchronisation, at every render; the copy made the first time is reused instead.
"""

from __future__ import annotations

import functools

import torch


@functools.cache
def on_device(constant: torch.Tensor, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """``constant`` on ``device`` as ``dtype``, shared by every caller: never modify it.

    Keyed on the constant's identity (tensors hash by ``id``), so pass module-level constants only.
    """
    return constant.to(device=device, dtype=dtype)
