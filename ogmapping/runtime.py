"""Process-wide thread settings that map fastest on a device."""

from __future__ import annotations

import os

import torch


def torch_threads_for(device: str | torch.device) -> int:
    """Intra-op torch threads for mapping on ``device``.

    On the CPU the mapper's remaining torch ops are small (decoders over a few thousand anchors,
    gathers, Adam): waking a second torch thread costs more than it saves (one thread ran a
    mapping iteration 1.2-1.4x faster on 7-Scenes, bench/RESULTS.md), while the compiled kernels
    bring their own Numba thread team. On CUDA, torch threads only serve host-side work.
    """
    if torch.device(device).type == "cpu":
        return 1
    return max(1, min(os.cpu_count() or 1, 8))
