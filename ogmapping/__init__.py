"""OG-Mapping: online dense mapping with octree-managed structured 3D Gaussians."""

import os
import sys
import warnings

# PyTorch and the Numba kernels each run an OpenMP thread pool. With the default active wait
# policy an idle pool spins and starves the other, which made CPU mapping about 10x slower.
# The policy is read when a pool starts, so it must be set before torch is imported.
if "torch" in sys.modules and os.environ.get("OMP_WAIT_POLICY", "").upper() != "PASSIVE":
    warnings.warn(
        "torch was imported before ogmapping: set OMP_WAIT_POLICY=PASSIVE in the environment (or import "
        "ogmapping first), otherwise the CPU rasterizer and torch's thread pools spin against each other",
        RuntimeWarning,
        stacklevel=2,
    )
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
