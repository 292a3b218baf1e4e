"""Torch threads for the mapper's own calls: one where every op is small.

A sparse map on the CPU runs only small torch ops around the compiled kernels (decoders over a few
thousand anchors, gathers, Adam over the anchors); with a second torch thread each of them pays to
wake it, and a (1800 x 36) @ (36 x 32) matmul takes 3-4x longer than on one thread
(bench/RESULTS.md). A dense map's hash table (2^19 entries per level) is large enough to want
every thread, as does anything on CUDA. torch's OpenMP build keeps the thread count per calling
thread, so a mapper changes it only for its own calls, not for the rest of the process.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


def mapping_threads(device: torch.device, encoding: str) -> int | None:
    """Torch threads for a mapper's calls, or None to leave the caller's setting alone."""
    return 1 if device.type == "cpu" and encoding == "anchor" else None


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
