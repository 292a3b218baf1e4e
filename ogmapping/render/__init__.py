"""One public entry, ``rasterize()``, over interchangeable backends.

Backends (all render colour, expected depth and alpha, and expose the screen-space gradient):
- ``torch``: pure PyTorch through autograd; the reference the others are checked against.
- ``cpu``: compiled CPU kernels with a hand-written backward (Numba).
- ``gsplat``: CUDA through ``gsplat.rasterization``.
``auto`` picks ``gsplat`` for CUDA tensors when it is installed and ``cpu`` otherwise.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

import torch

BACKENDS = ("torch", "cpu", "gsplat")

# Shared compositing rules: every backend must implement exactly these.
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
TRANSMITTANCE_MIN = 1e-4
COVARIANCE_BLUR = 0.3
NEAR_PLANE = 0.01


@dataclass
class RenderOutput:
    """What a backend returns.

    ``color`` (H, W, 3) is composited over ``background``; ``depth`` (H, W) is the expected depth
    (accumulated z divided by alpha, 0 where alpha is 0); ``alpha`` (H, W) the accumulated opacity.
    ``means2d`` (N, 2) holds the projected centres in pixels; after ``loss.backward()`` its
    ``.grad`` is the per-Gaussian screen-space gradient refinement uses. ``visible`` (N,) marks
    Gaussians that touched the image.
    """

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    means2d: torch.Tensor
    visible: torch.Tensor


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
