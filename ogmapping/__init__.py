"""OG-Mapping: online dense mapping with octree-managed structured 3D Gaussians."""

import os

# PyTorch and the Numba kernels each run an OpenMP thread pool. With the default active wait
# policy the idle pool spins and starves the other, which made CPU mapping about 10x slower.
# This must be set before either library starts its pool, hence here, before any import of them.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
