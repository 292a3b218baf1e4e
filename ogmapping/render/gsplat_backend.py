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
- projection: EWA with ``eps2d`` = the camera's ``blur`` added to the 2D covariance ("classic",
  no opacity compensation); centres with z < ``NEAR_PLANE`` are culled; the Jacobian clamps x/z,
  y/z at 0.3 tan(fov/2) beyond the image edge, as ``projection.FOV_MARGIN`` does. gsplat bounds
  each Gaussian by a tight box (our reference: a square), which changes only which tiles are
  visited, not any pixel value. Its kernels are built with fast math (``__expf``), so a Gaussian
  whose alpha lands within float rounding of 1/255 may be kept by one backend and skipped by
  the other.
- depth: "RGB+ED" composites each centre's camera z and divides by alpha (clamped at 1e-10), which
  is our expected depth and gives 0 where alpha is 0.
- ``means2d`` of culled Gaussians is 0 rather than their projection (gsplat leaves them
  uninitialised; the mirrors zero them); use it where ``visible``.
- batches: a step's views are rendered with one call per image size through gsplat 1.5.3's
  leading batch dimension (one scene and one camera per batch entry), which gsplat 1.5.0-1.5.2 lack.
  Each entry holds whole warps of Gaussians (``batch_rows``): gsplat's projection backward sums
  gradients over a warp's threads grouped by camera or Gaussian index, never by batch entry.
- dtype: gsplat takes float32 only; other inputs are cast to it and the outputs back.
- poses: gsplat's projection computes the viewmats' gradient when they require grad; the stack and
  cast that pass them in keep the graph, so each view's viewmat gets its own gradient.
- options (``RasterOptions``): ``antialiased`` is gsplat's ``rasterize_mode="antialiased"``, ``absgrad`` its
  ``absgrad=True`` (read from ``meta["means2d"].absgrad`` once backward has run). ``packed`` is its
  ``packed=True``, which returns ``means2d`` and ``radii`` only for the (entry, Gaussian) pairs kept, with
  their ``batch_ids`` and ``gaussian_ids``; they are scattered back to per-view arrays, so the output is
  the unpacked one's. Packed, one call renders one view: its projection backward sums a warp's gradients
  grouped by Gaussian index (the means') and camera index (the viewmats'), never by entry, and packed
  entries follow each other mid-warp, where whole warps per entry (``batch_rows``) cannot keep them apart.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable

import torch
from torch.nn.functional import pad
from torch.nn.utils.rnn import pad_sequence

from ogmapping.render.options import DEFAULT, RasterOptions
from ogmapping.render.output import RenderOutput
from ogmapping.render.rules import NEAR_PLANE
from ogmapping.render.views import Camera, Splats, check_batch, grouped, parameters

INSTALL_HINT = (
    "the gsplat backend needs gsplat 1.5.x (1.5.3 or later) with its CUDA kernels and a CUDA build of PyTorch: after "
    "`pip install -e '.[cuda]'`, `pip install --no-build-isolation --no-binary gsplat --no-deps --force-reinstall "
    "'gsplat>=1.5.3,<1.6'` builds the kernels once (needs nvcc), see docs/cuda.md"
)
SUPPORTED_MINOR = (1, 5)
FIRST_BATCHED_PATCH = 3  # gsplat 1.5.3 added the leading batch dimension ``rasterize_batch`` renders through
WARP = 32  # CUDA threads per warp
# Cuts a tensor of one gsplat call's layout into its views' (n_i, ...) parts.
Pieces = Callable[[torch.Tensor], list[torch.Tensor]]


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
    numbers = tuple(int(part) for part in re.findall(r"\d+", version)[:3])
    if numbers[:2] != SUPPORTED_MINOR:
        return f"gsplat {version} is installed, but this backend implements the rules of gsplat 1.5.x"
    if numbers[2:] < (FIRST_BATCHED_PATCH,):
        return f"gsplat {version} is installed, but this backend renders batches of views through gsplat >= 1.5.3"
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


def _screen_means(projected: torch.Tensor, pieces: Pieces, dtype: torch.dtype,
                  visible: list[torch.Tensor]) -> list[torch.Tensor]:
    """Per-view (n_i, 2) leaves whose ``.grad`` receives the screen-space gradient of ``projected``.

    gsplat renders from its own tensor ((B, 1, N, 2), or (nnz, 2) packed), so a plain view of it would
    never get a gradient; leaf mirrors keep the shared ``RenderOutput.means2d.grad`` contract. ``pieces``
    cuts a tensor shaped like ``projected`` into the views' (n_i, 2) parts; each mirror holds its view's
    values (0 where ``visible`` is False) and a backward hook on ``projected`` hands each its part of the
    gradient, accumulating as a leaf's ``.grad`` does.
    """
    parts = [part.masked_fill(~seen.unsqueeze(-1), 0.0)
             for part, seen in zip(pieces(projected.detach()), visible, strict=True)]
    mirrors = [part.to(dtype).clone() for part in parts]
    if not projected.requires_grad:
        return mirrors
    for mirror in mirrors:
        mirror.requires_grad_(True)

    def receive(grad: torch.Tensor) -> None:
        for mirror, part in zip(mirrors, pieces(grad.detach()), strict=True):
            part = part.to(dtype)
            mirror.grad = part.clone() if mirror.grad is None else mirror.grad + part

    projected.register_hook(receive)
    return mirrors


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


def rasterize(splats: Splats, camera: Camera, background: torch.Tensor | None = None,
              options: RasterOptions = DEFAULT) -> RenderOutput:
    """Render with gsplat; see ``ogmapping.render.rasterize`` for shapes and conventions."""
    return rasterize_batch([splats], [camera], background, options)[0]


def rasterize_batch(scenes: list[Splats], cameras: list[Camera], background: torch.Tensor | None = None,
                    options: RasterOptions = DEFAULT) -> list[RenderOutput]:
    """Scene i into camera i: one gsplat call per image size (and blur), per view where ``options.packed``;
    see ``ogmapping.render.rasterize_batch``."""
    require()
    check_batch(scenes, cameras)
    for scene in scenes:
        if scene.means.device.type != "cuda":
            raise ValueError(f"the gsplat backend renders CUDA tensors only, got {scene.means.device}")
    from gsplat import rasterization

    outputs: list[RenderOutput | None] = [None] * len(scenes)
    for group in call_groups(cameras, options.packed):
        rendered = render_group(rasterization, [scenes[i] for i in group], [cameras[i] for i in group], background,
                                options)
        for index, output in zip(group, rendered, strict=True):
            outputs[index] = output
    return outputs


def call_groups(cameras: list[Camera], packed: bool = False) -> list[list[int]]:
    """Indices of the cameras, grouped by image size and blur in order of first appearance: gsplat
    renders a batch into images of one size with one ``eps2d``; ``packed``, one view a call (see the
    module's docstring)."""
    if packed:
        return [[index] for index in range(len(cameras))]
    return grouped((*camera.size, camera.blur) for camera in cameras)


def batch_rows(counts: list[int]) -> int:
    """Gaussians per batch entry: the most any view has, rounded up to whole warps where there are
    several views.

    gsplat 1.5.3's projection backward runs one thread per (entry, Gaussian) and sums the viewmat's
    gradient over the threads of a warp grouped by camera index, the means' by Gaussian index, and
    never by entry: a warp that straddled two entries would add one view's share to the other's
    (a refined pose's gradient off by 20-30% on random scenes). Whole warps per entry keep each
    view's sums its own.
    """
    most = max(counts)
    return most if len(counts) == 1 else -(-most // WARP) * WARP


def _padded(tensors: list[torch.Tensor], rows: int) -> torch.Tensor:
    """The views' tensors stacked along a new first dimension, zero-padded to ``rows`` each."""
    stacked = pad_sequence(tensors, batch_first=True)
    return pad(stacked, (0, 0) * (stacked.dim() - 2) + (0, rows - stacked.shape[1]))


def render_group(
    rasterization: Callable[..., tuple[torch.Tensor, torch.Tensor, dict]],
    scenes: list[Splats],
    cameras: list[Camera],
    background: torch.Tensor | None,
    options: RasterOptions = DEFAULT,
) -> list[RenderOutput]:
    """One call of gsplat's ``rasterization`` for views of one image size and blur, each scene its own batch
    entry (gsplat 1.5.3's leading batch dimension), padded to ``batch_rows`` with Gaussians of
    opacity 0, which gsplat's projection culls before anything else reads them.

    gsplat's kernels take float32 only: inputs are cast to it and the outputs back to the dtype of
    the means, as the CPU backend does. Passed in (not imported here) so tests can stand in for it.
    """
    dtype, device, work = scenes[0].means.dtype, scenes[0].means.device, torch.float32
    width, height = cameras[0].size
    counts = [int(scene.means.shape[0]) for scene in scenes]
    if max(counts) == 0:
        return [_empty(scene.means, width, height, background) for scene in scenes]
    rows = batch_rows(counts)
    padded = [
        _padded([tensor.to(work) for tensor in tensors], rows)
        for tensors in zip(*(parameters(scene) for scene in scenes), strict=True)
    ]
    batch = len(scenes)
    render, alpha, meta = rasterization(
        *padded,
        torch.stack([camera.viewmat for camera in cameras]).to(device=device, dtype=work)[:, None],
        torch.stack([camera.K for camera in cameras]).to(device=device, dtype=work)[:, None],
        width,
        height,
        near_plane=NEAR_PLANE,
        eps2d=cameras[0].blur,
        packed=options.packed,
        absgrad=options.absgrad,
        render_mode="RGB+ED",
        rasterize_mode="antialiased" if options.antialiased else "classic",
        backgrounds=None if background is None else background.to(device=device, dtype=work).expand(batch, 1, 3),
    )
    pieces = _packed_pieces(meta, counts, rows) if options.packed else _batched_pieces(counts)
    visible = pieces((meta["radii"] > 0).all(dim=-1))  # a Gaussian is culled where either radius is 0
    # gsplat leaves the entries of culled Gaussians uninitialised (``at::empty``); the mirrors hold 0 there.
    means2d = _screen_means(meta["means2d"], pieces, dtype, visible)
    absolute = functools.partial(_absolute, meta["means2d"], pieces, visible) if options.absgrad else None
    return [
        RenderOutput(
            color=render[b, 0, ..., :3].to(dtype),
            depth=render[b, 0, ..., 3].to(dtype),
            alpha=alpha[b, 0, ..., 0].to(dtype),
            means2d=means2d[b],
            visible=visible[b],
            absgrad=None if absolute is None else functools.partial(absolute, b, dtype),
        )
        for b in range(batch)
    ]


def _batched_pieces(counts: list[int]) -> Pieces:
    """Cuts a tensor of gsplat's unpacked layout, (B, 1, N, ...), into the views' (n_i, ...) parts."""
    return lambda tensor: [tensor[b, 0, :count] for b, count in enumerate(counts)]


def _packed_pieces(meta: dict, counts: list[int], rows: int) -> Pieces:
    """Scatters a tensor of gsplat's packed layout, (nnz, ...) with ``meta["batch_ids"]`` and
    ``meta["gaussian_ids"]``, into the views' (n_i, ...) parts, 0 (False) for the Gaussians it left out."""
    index = (meta["batch_ids"], meta["gaussian_ids"])

    def pieces(tensor: torch.Tensor) -> list[torch.Tensor]:
        dense = tensor.new_zeros(len(counts), rows, *tensor.shape[1:]).index_put_(index, tensor)
        return [dense[b, :count] for b, count in enumerate(counts)]

    return pieces


def _absolute(projected: torch.Tensor, pieces: Pieces, visible: list[torch.Tensor], view: int,
              dtype: torch.dtype) -> torch.Tensor | None:
    """View ``view``'s (n, 2) part of the |gradient| sums gsplat's backward leaves in ``projected.absgrad``
    (0 where culled), or None before a backward has run."""
    summed = getattr(projected, "absgrad", None)
    if summed is None:
        return None
    return pieces(summed.detach())[view].masked_fill(~visible[view].unsqueeze(-1), 0.0).to(dtype)
