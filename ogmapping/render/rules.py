"""The compositing and projection rules every backend implements exactly (tests hold them to it).

A module of constants only, so backends, kernels and tests read them without importing the
package entry that dispatches to those backends.

``ALPHA_MAX`` is gsplat 1.5's cap, compiled into its forward and backward kernels
(``min(0.999f, ...)``), so that a map comes out the same on the CPU and on CUDA; the CPU and
reference kernels read it from here. gsplat's main branch after 1.5.3 caps at 0.99 instead: moving
to it means changing this value (and the version ``gsplat_backend`` accepts) with it. The compiled
CPU kernels freeze these values when they compile: see ``cpu_kernels`` for clearing their cache.
"""

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
COVARIANCE_BLUR = 0.3
NEAR_PLANE = 0.01
