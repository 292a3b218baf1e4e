"""OG-Mapping: online dense mapping with octree-managed structured 3D Gaussians."""

import os
import sys
import warnings

# PyTorch and the Numba kernels each run an OpenMP thread pool. Under libgomp's default active wait
# policy an idle pool spins for a long time and starves the other, which made CPU mapping about
# 10x slower; a purely passive policy puts workers to sleep at once, and waking them costs ~90 us
# per parallel region on this 2-core machine (a mapping iteration runs dozens). A short spin
# (libgomp's spin count for an undefined policy) keeps back-to-back regions cheap and still sleeps
# soon: 1.2x faster sparse and dense iterations (bench/RESULTS.md). Both are read when a pool
# starts, so they must be set before torch is imported.
if "torch" in sys.modules and os.environ.get("OMP_WAIT_POLICY", "").upper() != "PASSIVE":
    warnings.warn(
        "torch was imported before ogmapping: set OMP_WAIT_POLICY=PASSIVE in the environment (or import "
        "ogmapping first), otherwise the CPU rasterizer and torch's thread pools spin against each other",
        RuntimeWarning,
        stacklevel=2,
    )
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("GOMP_SPINCOUNT", "300000")

from ogmapping.runtime.allocator import keep_freed_memory

keep_freed_memory()

__version__ = "0.1.0"
