"""Device values the host reads: each read waits until the device has computed them.

The engine reads as few times as it can, several values at once (a frame's new-cell count with its
keyframe test, a refinement's counts per level with its pruning count), and every such read goes
through ``read``, which counts it: ``tolist`` dispatches no operator, so a profiler or a dispatch mode
would not see these waits, and the tests and benches that bound them add ``reads()``.
"""

from __future__ import annotations

import torch

_total = 0  # reads so far


def read(*values: torch.Tensor) -> list[float]:
    """Every element of ``values`` (flattened, in order) on the host, as float64 (exact for counts up to 2**53);
    nothing to read (no values) is no wait."""
    if not values:
        return []
    global _total
    _total += 1
    return torch.cat([value.detach().reshape(-1).to(torch.float64) for value in values]).tolist()


def reads() -> int:
    """How many reads this process has made."""
    return _total
