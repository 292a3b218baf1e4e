"""A count the device computes and the host reads a step later, without waiting for it.

Reading a device tensor on the host (``int(tensor)``) waits until the device has computed it, which
stops a step from running ahead of the GPU. A count only statistics and logs want (how many Gaussians
the last step drew) is copied off the device without blocking when it is made, and read when asked
for, by which time the copy has long finished. On the CPU there is nothing to wait for.
"""

from __future__ import annotations

import torch


class LateCount:
    """The newest posted count, readable on the host."""

    def __init__(self, value: int = 0) -> None:
        self._value: int | torch.Tensor = value
        self._ready: torch.cuda.Event | None = None

    def post(self, count: torch.Tensor | int) -> None:
        """Take ``count`` (a device tensor or a number) without waiting for it."""
        if isinstance(count, torch.Tensor) and count.device.type == "cuda":
            host = torch.empty((), dtype=count.dtype, pin_memory=True)
            host.copy_(count, non_blocking=True)
            self._ready = torch.cuda.Event()
            self._ready.record()
            count = host
        self._value = count

    def value(self) -> int:
        """The posted count (waits only for a copy posted moments ago)."""
        if self._ready is not None:
            self._ready.synchronize()
            self._ready = None
        return int(self._value)
