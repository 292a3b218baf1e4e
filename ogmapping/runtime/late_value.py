"""A value the device computes and the host reads later, without waiting for it when it is made.

Reading a device tensor on the host (``int(tensor)``) waits until the device has computed it, which
stops the mapper from running ahead of the GPU. A value only results, statistics and logs want (a
frame's last loss, how many Gaussians its last step drew) is copied off the device without blocking
when it is made, and read when asked for: by the caller that acknowledges the frame, after the
mapper has queued its work. On the CPU there is nothing to wait for.
"""

from __future__ import annotations

import torch


class LateValue:
    """The newest posted value, readable on the host."""

    def __init__(self, value: float = 0) -> None:
        self._value: float | torch.Tensor = value
        self._ready: torch.cuda.Event | None = None

    @classmethod
    def of(cls, value: torch.Tensor | float) -> LateValue:
        """A late value holding ``value``."""
        late = cls()
        late.post(value)
        return late

    def post(self, value: torch.Tensor | float) -> None:
        """Take ``value`` (a device tensor or a number) without waiting for it."""
        self._ready = None
        if isinstance(value, torch.Tensor):
            value = value.detach()
            if value.device.type == "cuda":
                host = torch.empty((), dtype=value.dtype, pin_memory=True)
                host.copy_(value, non_blocking=True)
                self._ready = torch.cuda.Event()
                self._ready.record()
                value = host
        self._value = value

    def snapshot(self) -> LateValue:
        """A late value that keeps what is posted now, whatever is posted here later."""
        late = LateValue(self._value)
        late._ready = self._ready
        return late

    def value(self) -> float:
        """The posted value (waits, on CUDA, until the device has made it)."""
        if self._ready is not None:
            self._ready.synchronize()
        return self._value.item() if isinstance(self._value, torch.Tensor) else self._value
