"""CUDA backend: the shared ``rasterize()`` signature over ``gsplat.rasterization`` (gsplat >= 1.4).

gsplat is imported lazily so the engine imports on machines without it. Its kernels follow the
shared rules of ``ogmapping.render`` with these differences (gsplat 1.5.x; fixed in its CUDA code,
not settable from Python):

- alpha cap: gsplat clamps per-pixel alpha to 0.999, ours is ``ALPHA_MAX`` = 0.99. Renders agree
  wherever opacity * G(x) <= 0.99; above that gsplat lets less light through.
- ``ALPHA_MIN``: the same 1/255 skip; gsplat also culls Gaussians whose opacity is below it.
- transmittance: a pixel stops *before* the Gaussian that would bring T to <= 1e-4
  (``TRANSMITTANCE_MIN``); that Gaussian does not contribute.
- projection: EWA with ``eps2d`` = ``COVARIANCE_BLUR`` added to the 2D covariance ("classic",
  no opacity compensation); centres with z < ``NEAR_PLANE`` are culled; the Jacobian clamps x/z,
  y/z at 0.3 tan(fov/2) beyond the image edge, as ``projection.FOV_MARGIN`` does. gsplat bounds
  each Gaussian by a tight box (our reference: a square), which changes only which tiles are
  visited, not any pixel value. Its kernels are built with fast math (``__expf``), so a Gaussian
  whose alpha lands within float rounding of 1/255 may be kept by one backend and skipped by
  the other.
- depth: "RGB+ED" composites each centre's camera z and divides by alpha (clamped at 1e-10), which
  is our expected depth and gives 0 where alpha is 0.
- ``means2d`` of culled Gaussians is 0 rather than their projection; use it where ``visible``.
"""

from __future__ import annotations

import torch

from ogmapping.render.output import RenderOutput
from ogmapping.render.rules import COVARIANCE_BLUR, NEAR_PLANE

INSTALL_HINT = (
    "the gsplat backend needs the gsplat package and a CUDA build of PyTorch: "
    "`pip install gsplat` (or `pip install -e '.[cuda]'`), see docs/cuda.md"
)


def _screen_means(projected: torch.Tensor) -> torch.Tensor:
    """(N, 2) pixel centres whose ``.grad`` receives gsplat's screen-space gradient.

    gsplat renders from its own (1, N, 2) tensor, so a plain view of it would never get a gradient;
    a leaf mirror filled by a backward hook keeps the shared ``means2d.grad`` contract.
    """
    mirror = projected[0].detach()
    if not projected.requires_grad:
        return mirror
    mirror.requires_grad_(True)

    def receive(grad: torch.Tensor) -> None:
        step = grad[0].detach()
        mirror.grad = step.clone() if mirror.grad is None else mirror.grad + step

    projected.register_hook(receive)
    return mirror


def _empty(means: torch.Tensor, width: int, height: int, background: torch.Tensor | None) -> RenderOutput:
    """The render of no Gaussians, which gsplat's tile binning does not accept."""
    color = torch.zeros(height, width, 3, dtype=means.dtype, device=means.device)
    if background is not None:
        color = color + background.to(color)
    zeros = torch.zeros(height, width, dtype=means.dtype, device=means.device)
    return RenderOutput(
        color=color,
        depth=zeros,
        alpha=zeros.clone(),
        means2d=means.new_zeros(0, 2),
        visible=torch.zeros(0, dtype=torch.bool, device=means.device),
    )


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
) -> RenderOutput:
    """Render with gsplat; see ``ogmapping.render.rasterize`` for shapes and conventions."""
    try:
        from gsplat import rasterization
    except ImportError as error:
        raise ImportError(INSTALL_HINT) from error
    if means.device.type != "cuda":
        raise ValueError(f"the gsplat backend renders CUDA tensors only, got {means.device}")
    if means.shape[0] == 0:
        return _empty(means, width, height, background)

    render, alpha, meta = rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmat.to(means)[None],
        K.to(means)[None],
        width,
        height,
        near_plane=NEAR_PLANE,
        eps2d=COVARIANCE_BLUR,
        packed=False,
        render_mode="RGB+ED",
        rasterize_mode="classic",
        backgrounds=None if background is None else background.to(means).reshape(1, 3),
    )
    radii = meta["radii"][0]  # (N, 2) in gsplat 1.5, (N,) in 1.4
    visible = (radii > 0).all(dim=-1) if radii.dim() == 2 else radii > 0
    return RenderOutput(
        color=render[0, ..., :3],
        depth=render[0, ..., 3],
        alpha=alpha[0, ..., 0],
        means2d=_screen_means(meta["means2d"]),
        visible=visible,
    )
