"""One public entry, ``rasterize()``, over interchangeable backends.

Backends (all render colour, expected depth and alpha, and expose the screen-space gradient):
- ``torch``: pure PyTorch through autograd; the reference the others are checked against.
- ``cpu``: compiled CPU kernels with a hand-written backward (Numba).
- ``gsplat``: CUDA through ``gsplat.rasterization``.
``auto`` picks ``cpu`` for CPU tensors and, for CUDA tensors, ``gsplat`` when it is installed,
else ``torch``. What every backend implements and returns lives in ``rules.py`` and ``output.py``,
which the backends import instead of this entry.
"""

from __future__ import annotations

import importlib

import torch

from ogmapping.backends import BACKENDS
from ogmapping.render.output import RenderOutput


def resolve_backend(backend: str, device: torch.device) -> str:
    """Turn ``auto`` into a concrete backend name for ``device``."""
    if backend != "auto":
        if backend not in BACKENDS:
            raise ValueError(f"unknown rasterizer backend {backend!r}; choose one of {', '.join(BACKENDS)}")
        return backend
    if device.type == "cuda" and importlib.util.find_spec("gsplat") is not None:
        return "gsplat"
    if device.type == "cuda":
        return "torch"
    return "cpu"


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    backend: str = "auto",
) -> RenderOutput:
    """Render N Gaussians into one camera.

    ``means`` (N, 3) world positions, ``quats`` (N, 4) (w, x, y, z) unnormalised rotations,
    ``scales`` (N, 3) standard deviations in metres, ``opacities`` (N,) in [0, 1], ``colors``
    (N, 3), ``viewmat`` (4, 4) world-to-camera, ``K`` (3, 3) pixel intrinsics (pixel centres at
    +0.5, see ``ogmapping.camera``).
    """
    name = resolve_backend(backend, means.device)
    module = importlib.import_module(f"ogmapping.render.{name}_backend")
    return module.rasterize(
        means, quats, scales, opacities, colors, viewmat, K, int(width), int(height), background
    )
