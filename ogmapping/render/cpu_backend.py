"""Compiled CPU rasterizer: Numba projection and compositing, each with a hand-written backward.

Four torch operators (``torch.library``: ``ogmapping::cpu_project``, ``cpu_composite`` and their
backwards), each one Numba stage to torch's dispatcher and profiler however many array conversions it
makes inside, chained by two ``autograd.Function``s: projection (``cpu_projection``) turns the Gaussian
parameters into screen-space means, conics, depths and radii, and compositing (``cpu_kernels``)
turns those into images. Keeping ``means2d`` a separate autograd node is what gives it the
``.grad`` refinement reads. Both run float32 kernels; results follow exactly the rules of the
torch reference and come back in the input dtype.

Both take a batch of views, each its own Gaussians and camera, concatenated (or stacked view first,
``rasterize_stacked``, which is the same rows without a copy): one projection node and one
compositing node per batch, whatever its size. The kernels still run view after view (each is
parallel within its image).
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numba
import numpy as np
import torch

from ogmapping.arrays import float32_array
from ogmapping.render import cpu_kernels as kernels
from ogmapping.render import cpu_projection
from ogmapping.render.output import RenderOutput, finish_output
from ogmapping.render.projection import Projection
from ogmapping.render.views import Camera, Splats, SplatSet, check_batch, parameters


def _depth_order(depths: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Visible indices front to back, equal depths in index order (the reference's stable sort).

    One plain sort of int64 keys, each a float32 depth's bits made to order as integers (negative
    values flipped) above its position: the keys are distinct, so any sort is stable, and numpy
    sorts int64 with its SIMD sort, about 10x faster than a stable argsort (float32 depths tie in
    most renders of a few ten thousand Gaussians, bench/RESULTS.md).
    """
    keys = depths[visible] + np.float32(0.0)  # -0.0 -> 0.0: the two are equal depths
    bits = keys.view(np.int32).astype(np.int64)
    bits ^= (bits >> 31) & 0x7FFFFFFF
    packed = (bits << 32) | np.arange(keys.size, dtype=np.int64)
    packed.sort()
    return visible[packed & 0xFFFFFFFF].astype(np.int32)


@dataclass(frozen=True)
class Layout:
    """Where each view's Gaussians sit in the concatenated inputs, and its image size."""

    counts: tuple[int, ...]
    sizes: tuple[tuple[int, int], ...]  # (width, height) per view
    blurs: tuple[float, ...]  # Camera.blur per view

    @functools.cached_property
    def spans(self) -> list[slice]:
        return [slice(int(a), int(b)) for a, b in itertools.pairwise(np.cumsum((0, *self.counts)))]

    @property
    def arguments(self) -> tuple[list[int], list[int], list[float]]:
        """The layout as the kernels' torch ops take it: counts, flattened sizes, blurs."""
        return list(self.counts), [n for size in self.sizes for n in size], list(self.blurs)

    @classmethod
    def of(cls, counts: list[int], sizes: list[int], blurs: list[float]) -> Layout:
        return cls(tuple(counts), tuple(zip(sizes[0::2], sizes[1::2], strict=True)), tuple(blurs))


# The kernels as torch operators (``torch.library``): each stage one operator to torch's dispatcher,
# profiler and tracing, however many array conversions it makes inside; the autograd functions below
# chain them.

@torch.library.custom_op("ogmapping::cpu_project", mutates_args=())
def _project(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
             viewmats: torch.Tensor, Ks: torch.Tensor, counts: list[int], sizes: list[int],
             blurs: list[float]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every view's (means2d, conics, depths, radii), concatenated, float32."""
    layout = Layout.of(counts, sizes, blurs)
    inputs = [float32_array(t) for t in (means, quats, scales, opacities)]
    viewmats_np, Ks_np = float32_array(viewmats), float32_array(Ks)
    per_view = [
        cpu_projection.project_forward(*(a[span] for a in inputs), viewmats_np[v], Ks_np[v], *layout.sizes[v],
                                       layout.blurs[v])
        for v, span in enumerate(layout.spans)
    ]
    return tuple(torch.from_numpy(np.concatenate(parts)) for parts in zip(*per_view, strict=True))


@torch.library.custom_op("ogmapping::cpu_project_backward", mutates_args=())
def _project_backward(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                      viewmats: torch.Tensor, Ks: torch.Tensor, grad_means2d: torch.Tensor | None,
                      grad_conics: torch.Tensor | None, grad_depths: torch.Tensor | None, counts: list[int],
                      sizes: list[int], blurs: list[float], camera: bool
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gradients of means, quats, scales and (empty unless ``camera``) the viewmats, float32."""
    layout = Layout.of(counts, sizes, blurs)
    inputs = [float32_array(t) for t in (means, quats, scales, opacities)]
    viewmats_np, Ks_np = float32_array(viewmats), float32_array(Ks)
    n = inputs[0].shape[0]
    upstream = [
        np.zeros(shape, np.float32) if g is None else float32_array(g)
        for g, shape in ((grad_means2d, (n, 2)), (grad_conics, (n, 3)), (grad_depths, (n,)))
    ]
    per_view = [
        cpu_projection.project_backward(*(a[span] for a in inputs), viewmats_np[v], Ks_np[v], *layout.sizes[v],
                                        layout.blurs[v], *(g[span] for g in upstream), camera)
        for v, span in enumerate(layout.spans)
    ]
    *gaussian_parts, viewmat_parts = zip(*per_view, strict=True)
    grads = [np.concatenate(parts) for parts in gaussian_parts]
    grads.append(np.stack(viewmat_parts) if camera else np.zeros(0, np.float32))
    return tuple(torch.from_numpy(g) for g in grads)


# Per view, what compositing's backward needs of its forward: the depth order, the tile bins (tile
# offsets, ids, pair start, pair of), the ellipses (limits, extents), the final transmittance and the
# contributor counts; passed between the two operators as tensors.
_STATE_PER_VIEW = 9


@torch.library.custom_op("ogmapping::cpu_composite", mutates_args=())
def _composite(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, colors: torch.Tensor,
               depths: torch.Tensor, background: torch.Tensor, radii: torch.Tensor, counts: list[int],
               sizes: list[int], blurs: list[float]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Each view's images (all colours, then all accumulated depths, then all alphas, float32) and the
    state its backward takes."""
    layout = Layout.of(counts, sizes, blurs)
    arrays = [float32_array(t) for t in (means2d, conics, opacities, colors, depths)]
    bg = float32_array(background)
    radii_np = np.ascontiguousarray(radii.to("cpu", torch.int32).numpy())
    n_threads = numba.get_num_threads()
    images, state = [], []
    for span, (width, height) in zip(layout.spans, layout.sizes, strict=True):
        m2d, con, opa, col, dep = (a[span] for a in arrays)
        order = _depth_order(dep, np.flatnonzero(radii_np[span] > 0))
        tile_offsets, ids, pair_start, pair_of, limits, extents = kernels.bin_tiles(
            order, m2d, con, opa, radii_np[span], width, height, n_threads
        )
        color, accum_depth, final_t, n_contrib = kernels.render_forward(
            tile_offsets, ids, m2d, con, opa, col, dep, limits, extents, bg, width, height, n_threads
        )
        images.append((color, accum_depth, 1.0 - final_t))
        state += (order, tile_offsets, ids, pair_start, pair_of, limits, extents, final_t, n_contrib)
    return ([torch.from_numpy(image) for kind in zip(*images, strict=True) for image in kind],
            [torch.from_numpy(np.asarray(array)) for array in state])


@torch.library.custom_op("ogmapping::cpu_composite_backward", mutates_args=())
def _composite_backward(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, colors: torch.Tensor,
                        depths: torch.Tensor, background: torch.Tensor, state: list[torch.Tensor],
                        grads: list[torch.Tensor | None], counts: list[int], sizes: list[int], blurs: list[float]
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gradients of means2d, conics, opacities, colours, depths and the background, float32 (the
    background's float64); ``grads`` all colours', then all depths', then all alphas'."""
    layout = Layout.of(counts, sizes, blurs)
    arrays = [float32_array(t) for t in (means2d, conics, opacities, colors, depths)]
    bg = float32_array(background)
    count = len(layout.counts)
    n_threads = numba.get_num_threads()
    gaussian_grads, bg_grad = [], np.zeros(3, np.float64)
    for v, (span, (width, height)) in enumerate(zip(layout.spans, layout.sizes, strict=True)):
        m2d, con, opa, col, dep = (a[span] for a in arrays)
        order, tile_offsets, ids, pair_start, pair_of, limits, extents, final_t, n_contrib = (
            t.numpy() for t in state[v * _STATE_PER_VIEW:(v + 1) * _STATE_PER_VIEW])
        upstream = [
            np.zeros(shape, np.float32) if g is None else float32_array(g)
            for g, shape in ((grads[v], (height, width, 3)), (grads[count + v], (height, width)),
                             (grads[2 * count + v], (height, width)))
        ]
        pair_grads, bg_grads = kernels.render_backward(
            tile_offsets, ids, m2d, con, opa, col, dep, limits, extents, bg, final_t, n_contrib,
            *upstream, width, height, n_threads,
        )
        gaussian_grads.append(kernels.reduce_pairs(order, pair_start, pair_of, pair_grads, m2d.shape[0]))
        bg_grad += bg_grads.sum(axis=0, dtype=np.float64)
    grads_np = np.concatenate(gaussian_grads)
    parts = (grads_np[:, 0:2], grads_np[:, 2:5], grads_np[:, 5], grads_np[:, 6:9], grads_np[:, 9])
    return (*(torch.from_numpy(np.ascontiguousarray(part)) for part in parts), torch.from_numpy(bg_grad))


def _like(t: torch.Tensor, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A kernel's float32 CPU result in the caller's dtype and device (no operator when they match)."""
    return t if t.dtype == dtype and t.device == device else t.to(dtype=dtype, device=device)


class _Project(torch.autograd.Function):
    """Gaussian parameters and cameras -> (means2d, conics, depths, radii) of every view, concatenated;
    opacity only culls, so gets no gradient. Each view's viewmat gets its gradient only when the
    stacked viewmats need one, so fixed poses cost nothing; intrinsics get none."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, layout):
        means2d, conics, depths, radii = _project(means, quats, scales, opacities, viewmats, Ks, *layout.arguments)
        ctx.save_for_backward(means, quats, scales, opacities, viewmats, Ks)
        ctx.layout = layout
        ctx.dtypes = (means.dtype, quats.dtype, scales.dtype, viewmats.dtype)
        radii = _like(radii, radii.dtype, means.device)
        ctx.mark_non_differentiable(radii)
        return (*(_like(t, means.dtype, means.device) for t in (means2d, conics, depths)), radii)

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, grad_depths, _grad_radii):
        camera = ctx.needs_input_grad[4]
        saved = ctx.saved_tensors
        grads = _project_backward(*saved, grad_means2d, grad_conics, grad_depths, *ctx.layout.arguments, camera)
        device = saved[0].device
        means, quats, scales, viewmats = (_like(g, dtype, device) for g, dtype in zip(grads, ctx.dtypes, strict=True))
        return means, quats, scales, None, viewmats if camera else None, None, None


class _Composite(torch.autograd.Function):
    """Screen-space Gaussians of every view -> each view's (colour, accumulated depth, alpha) images,
    returned as all colours, then all depths, then all alphas."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, radii, layout):
        images, state = _composite(means2d, conics, opacities, colors, depths, background, radii, *layout.arguments)
        ctx.save_for_backward(means2d, conics, opacities, colors, depths, background, *state)
        ctx.layout = layout
        ctx.dtypes = (means2d.dtype, background.dtype)
        return tuple(_like(image, means2d.dtype, means2d.device) for image in images)

    @staticmethod
    def backward(ctx, *grads):
        saved = ctx.saved_tensors
        *gaussian_grads, grad_bg = _composite_backward(*saved[:6], list(saved[6:]), list(grads),
                                                       *ctx.layout.arguments)
        dtype, bg_dtype = ctx.dtypes
        device = saved[0].device
        return (*(_like(g, dtype, device) for g in gaussian_grads), _like(grad_bg, bg_dtype, device), None, None)


def rasterize(splats: Splats, camera: Camera, background: torch.Tensor | None = None) -> RenderOutput:
    """Render with the compiled kernels; see ``ogmapping.render.rasterize`` for the arguments.

    ``viewmat`` may require grad (pose refinement); intrinsics are fixed here: the projection's
    backward has no gradient for ``K``, so asking for one is an error rather than a silent zero.
    """
    return rasterize_batch([splats], [camera], background)[0]


def rasterize_batch(scenes: list[Splats], cameras: list[Camera],
                    background: torch.Tensor | None = None) -> list[RenderOutput]:
    """Render scene i into camera i with one projection and one compositing node for all of them;
    see ``ogmapping.render.rasterize_batch``."""
    check_batch(scenes, cameras)
    concatenated = SplatSet(*(torch.cat(tensors) if len(scenes) > 1 else tensors[0]
                              for tensors in zip(*(parameters(scene) for scene in scenes), strict=True)))
    return _render(concatenated, tuple(int(scene.means.shape[0]) for scene in scenes), cameras, background)


def rasterize_stacked(scenes: Splats, cameras: list[Camera],
                      background: torch.Tensor | None = None) -> list[RenderOutput]:
    """``rasterize_batch`` of scenes stacked view first, (V, N, ...): their rows are already the
    concatenation the kernels take, so nothing is copied."""
    views, count = scenes.means.shape[:2]
    check_batch(range(views), cameras)
    flat = SplatSet(*(t.flatten(0, 1) for t in parameters(scenes)))
    return _render(flat, (int(count),) * views, cameras, background)


def _render(splats: Splats, counts: tuple[int, ...], cameras: list[Camera],
            background: torch.Tensor | None) -> list[RenderOutput]:
    """Every view's Gaussians, concatenated (``counts`` rows each), into its camera."""
    if any(camera.K.requires_grad for camera in cameras):
        raise NotImplementedError("the cpu backend has no gradient for K; use backend='torch'")
    means, quats, scales, opacities, colors = parameters(splats)
    layout = Layout(counts, tuple((int(camera.width), int(camera.height)) for camera in cameras),
                    tuple(float(camera.blur) for camera in cameras))
    viewmats = torch.stack([camera.viewmat for camera in cameras])
    Ks = torch.stack([camera.K for camera in cameras])
    proj = Projection(*_Project.apply(means, quats, scales, opacities, viewmats, Ks, layout))
    # Each view's means2d a piece of the projection that compositing reads, so its retained .grad is
    # that view's screen-space gradient and it stays differentiable, as the reference's is.
    count = len(cameras)
    means2d = list(proj.means2d.split(layout.counts)) if count > 1 else [proj.means2d]
    if proj.means2d.requires_grad:
        for piece in means2d:
            piece.retain_grad()
    bg = torch.zeros(3, dtype=means.dtype, device=means.device) if background is None else background.to(means)
    images = _Composite.apply(torch.cat(means2d) if count > 1 else means2d[0], proj.conics, opacities, colors,
                              proj.depths, bg, proj.radii, layout)
    radii = proj.radii.split(layout.counts) if count > 1 else [proj.radii]
    return [finish_output(images[v], images[count + v], images[2 * count + v], means2d[v], radii[v])
            for v in range(count)]
