"""Torch threads for one block of calls on the calling thread only.

torch's OpenMP build keeps the thread count per calling thread, so a mapper changes it for its own
calls (``ExecutionProfile.threads``) without changing it for the rest of the process: the server's
other sessions, evaluation.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def torch_threads(count: int | None) -> Iterator[None]:
    """Run the block with ``count`` torch threads on this thread (None: unchanged)."""
    if count is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
