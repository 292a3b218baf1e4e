"""Pay the engine's one-time costs before the first client does (the server) or the clock starts (``ogmap run``).

A fresh process loads each compiled kernel from Numba's cache on its first call, and torch imports
its compiler stack the first time an optimiser is built: together about 2 s on the development
machine (bench/RESULTS.md), which would otherwise land on the first mapping session's first frame.
Where the step runs as compiled graphs (CUDA), the throwaway map is made at two image sizes, so the
graphs are compiled for any size (torch makes a size a symbol once it has seen it change) before a
session's first frame rather than during it.
"""

from __future__ import annotations

import time

import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper

# Small enough to take well under a second once the kernels are loaded.
_SETTINGS = {"keyframes.first_iterations": 2, "keyframes.iterations": 1}
SIZES = ((64, 48), (80, 60))  # the second only where the step compiles graphs


def warm_up(device: str | torch.device = "cpu", backend: str = "auto", step: str = "auto") -> float:
    """Map two tiny synthetic frames, render and snapshot a throwaway map with ``backend`` and ``step``
    (config keys); returns the seconds taken. On CUDA this also pays for the context, the libraries'
    start and the first kernel loads."""
    start = time.perf_counter()
    for width, height in SIZES:
        source = SyntheticSource(n_frames=2, width=width, height=height)
        mapper = Mapper(resolve("sparse", overrides={**_SETTINGS, "backend": backend, "step": step}), device)
        for position in range(len(source)):
            mapper.process(source[position])
        frame = source[0]
        mapper.render(frame.c2w, frame.color_intrinsics)
        mapper.snapshot()
        if not mapper.profile.graphs:
            break
    return time.perf_counter() - start
