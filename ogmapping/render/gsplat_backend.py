"""CUDA backend: the shared ``rasterize()`` signature over ``gsplat.rasterization`` (gsplat 1.5.x).

gsplat is imported lazily so the engine imports on machines without it. ``unavailable_reason``
says whether it can render here: the package may be missing, of another minor version (1.4 bounds
Gaussians at 3 sigma and does not cull by opacity; gsplat's main branch after 1.5.3 caps alpha at
0.99), or installed without its compiled kernels, which gsplat 1.5 reports only by setting
``gsplat.cuda._backend._C`` to None, so that every render would fail.

Its kernels follow the shared rules of ``ogmapping.render`` (gsplat 1.5.x; fixed in its CUDA
code, not settable from Python), with these details:

- alpha cap: gsplat clamps per-pixel alpha to 0.999 in forward and backward, which is why
  ``ALPHA_MAX`` is 0.999 for every backend.
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
- ``means2d`` of culled Gaussians is 0 rather than their projection (gsplat leaves them
  uninitialised; ``_screen_means`` zeroes them); use it where ``visible``.
- dtype: gsplat takes float32 only; other inputs are cast to it and the outputs back.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch

from ogmapping.render.output import RenderOutput
from ogmapping.render.rules import COVARIANCE_BLUR, NEAR_PLANE

INSTALL_HINT = (
    "the gsplat backend needs gsplat 1.5.x with its CUDA kernels and a CUDA build of PyTorch: after "
    "`pip install -e '.[cuda]'`, `pip install --no-build-isolation --no-binary gsplat --no-deps --force-reinstall "
    "'gsplat>=1.5,<1.6'` builds the kernels once (needs nvcc), see docs/cuda.md"
)
SUPPORTED_MINOR = (1, 5)


@functools.cache
def unavailable_reason() -> str | None:
    """Why gsplat cannot render on this machine, or None when it can.

    Cached: the first call imports gsplat's compiled module, which gsplat builds just in time (for
    minutes) when it finds nvcc and no compiled kernels.
    """
    try:
        import gsplat
    except ImportError as error:
        return f"gsplat is not installed ({error})"
    version = gsplat.__version__
    if tuple(int(part) for part in version.split(".")[:2]) != SUPPORTED_MINOR:
        return f"gsplat {version} is installed, but this backend implements the rules of gsplat 1.5.x"
    try:
        from gsplat.cuda._backend import _C
    except Exception as error:  # its just-in-time build can fail in any way the compiler does
        return f"gsplat {version} could not load its CUDA kernels ({type(error).__name__}: {error})"
    if _C is None:
        return (f"gsplat {version} is installed without compiled CUDA kernels, and found no CUDA toolkit "
                "(nvcc) to build them")
    return None


def require() -> None:
    """Raise ImportError with the reason and the install hint when gsplat cannot render here."""
    reason = unavailable_reason()
    if reason is not None:
        raise ImportError(f"{reason}; {INSTALL_HINT}")


def _screen_means(projected: torch.Tensor, visible: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """(N, 2) pixel centres in ``dtype`` whose ``.grad`` receives gsplat's screen-space gradient.

    gsplat renders from its own (1, N, 2) tensor, so a plain view of it would never get a gradient;
    a leaf mirror filled by a backward hook keeps the shared ``means2d.grad`` contract. gsplat leaves
    the entries of culled Gaussians uninitialised (``at::empty``); the mirror holds 0 there.
    """
    mirror = projected[0].detach().masked_fill(~visible.unsqueeze(-1), 0.0).to(dtype)
    if not projected.requires_grad:
        return mirror
    mirror.requires_grad_(True)

    def receive(grad: torch.Tensor) -> None:
        step = grad[0].detach().to(dtype)
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
    require()
    if means.device.type != "cuda":
        raise ValueError(f"the gsplat backend renders CUDA tensors only, got {means.device}")
    if means.shape[0] == 0:
        return _empty(means, width, height, background)
    from gsplat import rasterization

    gaussians = (means, quats, scales, opacities, colors)
    return render_with(rasterization, gaussians, viewmat, K, width, height, background)


def render_with(
    rasterization: Callable[..., tuple[torch.Tensor, torch.Tensor, dict]],
    gaussians: tuple[torch.Tensor, ...],
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None,
) -> RenderOutput:
    """One call of gsplat's ``rasterization`` on ``gaussians`` (means, quats, scales, opacities, colours).

    gsplat's kernels take float32 only: inputs are cast to it and the outputs back to the dtype of
    the means, as the CPU backend does. Passed in (not imported here) so tests can stand in for it.
    """
    dtype, device, work = gaussians[0].dtype, gaussians[0].device, torch.float32
    render, alpha, meta = rasterization(
        *(tensor.to(work) for tensor in gaussians),
        viewmat.to(device=device, dtype=work)[None],
        K.to(device=device, dtype=work)[None],
        width,
        height,
        near_plane=NEAR_PLANE,
        eps2d=COVARIANCE_BLUR,
        packed=False,
        render_mode="RGB+ED",
        rasterize_mode="classic",
        backgrounds=None if background is None else background.to(device=device, dtype=work).reshape(1, 3),
    )
    visible = (meta["radii"][0] > 0).all(dim=-1)  # (N, 2): a Gaussian is culled where either radius is 0
    return RenderOutput(
        color=render[0, ..., :3].to(dtype),
        depth=render[0, ..., 3].to(dtype),
        alpha=alpha[0, ..., 0].to(dtype),
        means2d=_screen_means(meta["means2d"], visible, dtype),
        visible=visible,
    )
