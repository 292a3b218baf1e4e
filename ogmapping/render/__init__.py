"""One public entry, ``rasterize()`` (and ``rasterize_batch()`` for several views), over interchangeable backends.

Backends (all render colour, expected depth and alpha, expose the screen-space gradient, and give
a camera's ``viewmat`` its gradient when it requires one, for pose refinement):
- ``torch``: pure PyTorch through autograd; the reference the others are checked against.
- ``cpu``: compiled CPU kernels with a hand-written backward (Numba).
- ``gsplat``: CUDA through ``gsplat.rasterization``.
``auto`` picks ``cpu`` for CPU tensors and, for CUDA tensors, ``gsplat`` when it can render there
(``gsplat_backend.unavailable_reason``), else ``torch`` with a warning. What every backend
implements and returns lives in ``rules.py`` and ``output.py``, which the backends import instead
of this entry. ``RasterOptions`` (``options.py``) are gsplat's options beyond those rules; a backend
that does not implement one that is set refuses it (ValueError).
"""

from __future__ import annotations

import importlib
import warnings

import torch

from ogmapping.backends import BACKENDS
from ogmapping.render import gsplat_backend
from ogmapping.render.options import RasterOptions
from ogmapping.render.output import RenderOutput
from ogmapping.render.views import Camera, Splats, SplatSet, per_view

__all__ = ["Camera", "RasterOptions", "RenderOutput", "SplatSet", "Splats", "rasterize", "rasterize_batch",
           "resolve_backend"]


def resolve_backend(backend: str, device: torch.device) -> str:
    """Turn ``auto`` into a concrete backend name for ``device``.

    ``gsplat`` asked for by name must be able to render (ImportError with the install hint
    otherwise); ``auto`` on CUDA falls back to the pure-torch reference, with a RuntimeWarning
    that says why, because that reference takes seconds per 640x480 render.
    """
    if backend not in (*BACKENDS, "auto"):
        raise ValueError(f"unknown rasterizer backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend == "gsplat":
        gsplat_backend.require()
    if backend != "auto":
        return backend
    if device.type != "cuda":
        return "cpu"
    reason = gsplat_backend.unavailable_reason()
    if reason is None:
        return "gsplat"
    warnings.warn(f"{reason}; mapping on {device} falls back to the pure-torch reference rasterizer, which takes "
                  f"seconds per 640x480 render; {gsplat_backend.INSTALL_HINT}", RuntimeWarning, stacklevel=2)
    return "torch"


def rasterize(
    splats: Splats, camera: Camera, background: torch.Tensor | None = None, backend: str = "auto",
    options: RasterOptions | None = None,
) -> RenderOutput:
    """Render N Gaussians, ``splats``, into one ``camera``.

    ``splats.means`` (N, 3) world positions, ``quats`` (N, 4) (w, x, y, z) unnormalised rotations,
    ``scales`` (N, 3) standard deviations in metres, ``opacities`` (N,) in [0, 1], ``colors`` (N, 3);
    ``camera.viewmat`` (4, 4) world-to-camera, ``K`` (3, 3) pixel intrinsics (pixel centres at +0.5,
    see ``ogmapping.frames.camera``). ``camera.blur`` (pixels^2) is added to every splat's 2D
    covariance so that none is thinner than a pixel; an image sampling every s-th pixel of another
    (``Intrinsics.strided``) reproduces that image's pixels with ``blur / s**2``. ``options``: see
    ``RasterOptions``.
    """
    name = resolve_backend(backend, splats.means.device)
    module = importlib.import_module(f"ogmapping.render.{name}_backend")
    return module.rasterize(splats, camera, background, **_options(name, options))


def rasterize_batch(
    scenes: list[Splats] | Splats,
    cameras: list[Camera],
    background: torch.Tensor | None = None,
    backend: str = "auto",
    options: RasterOptions | None = None,
) -> list[RenderOutput]:
    """Render scene i (its own Gaussians, as ``rasterize`` takes them) into camera i, for every i.

    ``scenes`` is a list, or one ``Splats`` whose tensors are stacked view first ((V, N, ...), every
    view the same count, as a static-shape decode makes them): the ``cpu`` backend takes those as
    one batch without concatenating (nor, in backward, splitting) them; the others per view.

    The same images and gradients as one ``rasterize`` per view (the reference backend is exactly
    that loop), in as few backend calls as the backend can: ``cpu`` one projection and one
    compositing node for the whole batch, ``gsplat`` one call per image size (per view with
    ``options.packed``). Each output's
    ``means2d.grad`` holds its own view's screen-space gradient after ``backward``.
    """
    stacked = not isinstance(scenes, list | tuple)
    device = scenes.means.device if stacked else scenes[0].means.device if scenes else torch.device("cpu")
    name = resolve_backend(backend, device)
    module = importlib.import_module(f"ogmapping.render.{name}_backend")
    keywords = _options(name, options)
    if stacked and name == "cpu":
        return module.rasterize_stacked(scenes, list(cameras), background)
    return module.rasterize_batch(per_view(scenes), list(cameras), background, **keywords)


def _options(backend: str, options: RasterOptions | None) -> dict[str, RasterOptions]:
    """The keyword arguments that hand ``options`` to ``backend``: only gsplat takes them; the others render
    as every backend does, which is what ``packed`` asks for too, and refuse the rest (``RasterOptions.check``)."""
    if options is None:
        return {}
    options.check(backend)
    return {"options": options} if backend == "gsplat" else {}
