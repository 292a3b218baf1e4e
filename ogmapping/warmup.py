"""Pay the engine's one-time costs before the first client does (the server) or the clock starts (``ogmap run``).

A fresh process loads each compiled kernel from Numba's cache on its first call, and torch imports
its compiler stack the first time an optimiser is built: together about 2 s on the development
machine (bench/RESULTS.md), which would otherwise land on the first mapping session's first frame.
Where the step runs as compiled graphs (CUDA), the throwaway map is made at two image sizes, so the
graphs are compiled for any size (torch makes a size a symbol once it has seen it change) before a
session's first frame rather than during it.

On a first start the kernels are not in Numba's cache yet and are compiled: minutes on a slow CPU. So
``warm_up`` reports each stage as it ends (the server logs them, ``LocalServer`` takes each line as
progress), and ``python -m ogmapping.warmup`` (what ``make venv`` runs once) fills the cache ahead of time.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper

# Small enough to take well under a second once the kernels are loaded.
_SETTINGS = {"keyframes.first_iterations": 2, "keyframes.iterations": 1}
SIZES = ((64, 48), (80, 60))  # the second only where the step compiles graphs

Progress = Callable[[str, float], None]
"""Called with a stage's name and the seconds since the warm-up began, as each stage ends."""


def warm_up(device: str | torch.device = "cpu", backend: str = "auto", step: str = "auto",
            progress: Progress | None = None) -> float:
    """Map two tiny synthetic frames, render and snapshot a throwaway map with ``backend`` and ``step``
    (config keys); returns the seconds taken. On CUDA this also pays for the context, the libraries'
    start and the first kernel loads. ``progress`` hears of each stage as it ends."""
    start = time.perf_counter()

    def done(stage: str) -> None:
        if progress is not None:
            progress(stage, time.perf_counter() - start)

    for width, height in SIZES:
        source = SyntheticSource(n_frames=2, width=width, height=height)
        mapper = Mapper(resolve("sparse", overrides={**_SETTINGS, "backend": backend, "step": step}), device)
        for position in range(len(source)):
            mapper.process(source[position])
            done(f"{width}x{height} frame {position + 1} of {len(source)} mapped")
        frame = source[0]
        mapper.render(frame.c2w, frame.color_intrinsics)
        done(f"{width}x{height} render")
        mapper.snapshot()
        done(f"{width}x{height} snapshot")
        if not mapper.profile.graphs:
            break
    return time.perf_counter() - start


def main() -> int:
    """Compile (or load) the CPU kernels into Numba's cache, saying so, so a first server start does not."""
    print("compiling the mapping kernels into Numba's cache, once (a few minutes on a slow CPU; "
          "later starts load them in seconds)", flush=True)
    seconds = warm_up("cpu", progress=lambda stage, elapsed: print(f"  {stage}: {elapsed:.1f} s", flush=True))
    print(f"kernels ready: {seconds:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
