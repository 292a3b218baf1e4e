"""Rasterizer options beyond the shared rules (``rules.py``): gsplat 1.5's packed layout, absolute
screen-space gradients and antialiased projection. The defaults render as every backend does.

- ``packed``: gsplat keeps only the (view, Gaussian) pairs that pass its culling instead of arrays of
  every Gaussian per view: less memory where a view sees a small share of the map, the same images and
  gradients (``gsplat_backend`` hands them back unpacked). The other backends render the same without
  it, so they ignore it.
- ``absgrad``: gsplat's backward also sums each Gaussian's |gradient| over the pixels it touches
  (AbsGS), which ``RenderOutput.screen_gradient(absolute=True)`` reads. gsplat only.
- ``antialiased``: gsplat scales each Gaussian's opacity by sqrt(det(S) / det(S + blur I)) of its 2D
  covariance S (Mip-Splatting's compensation of the blur): another image. gsplat only.
"""

from __future__ import annotations

from dataclasses import dataclass

GSPLAT_ONLY = ("absgrad", "antialiased")  # options that change what a backend returns


@dataclass(frozen=True)
class RasterOptions:
    """What a render asks of its backend beyond the shared rules (see the module's docstring)."""

    packed: bool = False
    absgrad: bool = False
    antialiased: bool = False

    def check(self, backend: str) -> None:
        """ValueError naming the options set here that ``backend`` does not implement."""
        if backend == "gsplat":
            return
        asked = [name for name in GSPLAT_ONLY if getattr(self, name)]
        if asked:
            names = ", ".join(f"render.{name}" for name in asked)
            raise ValueError(f"{names}: gsplat's options only (backend gsplat, on CUDA); this map renders with "
                             f"the {backend} backend")


DEFAULT = RasterOptions()  # what every backend renders
