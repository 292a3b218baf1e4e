"""The compositing and projection rules every backend implements exactly (tests hold them to it).

A module of constants only, so backends, kernels and tests read them without importing the
package entry that dispatches to those backends.
"""

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
TRANSMITTANCE_MIN = 1e-4
COVARIANCE_BLUR = 0.3
NEAR_PLANE = 0.01
