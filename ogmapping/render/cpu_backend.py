"""Compiled CPU rasterizer: Numba projection and compositing, each with a hand-written backward.

Two ``autograd.Function``s chained by autograd: projection (``cpu_projection``) turns the Gaussian
parameters into screen-space means, conics, depths and radii, and compositing (``cpu_kernels``)
turns those into images. Keeping ``means2d`` a separate autograd node is what gives it the
``.grad`` refinement reads. Both run float32 kernels; results follow exactly the rules of the
torch reference and come back in the input dtype.

Both take a batch of views, each its own Gaussians and camera, concatenated: one projection node
and one compositing node per batch, whatever its size, so a mapping step's window costs two
autograd nodes and one conversion of each input, not two nodes and a dozen conversions per view.
The kernels still run view after view (each is parallel within its image).
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
from ogmapping.render.views import Camera, Splats, check_batch, parameters


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


class _Project(torch.autograd.Function):
    """Gaussian parameters and cameras -> (means2d, conics, depths, radii) of every view, concatenated;
    opacity only culls, so gets no gradient. Each view's viewmat gets its gradient only when the
    stacked viewmats need one, so fixed poses cost nothing; intrinsics get none."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, layout):
        inputs = [float32_array(t) for t in (means, quats, scales, opacities)]
        cameras = float32_array(viewmats), float32_array(Ks)
        per_view = [
            cpu_projection.project_forward(*(a[span] for a in inputs), cameras[0][v], cameras[1][v], *layout.sizes[v],
                                           layout.blurs[v])
            for v, span in enumerate(layout.spans)
        ]
        means2d, conics, depths, radii = (np.concatenate(parts) for parts in zip(*per_view, strict=True))
        ctx.state = (inputs, cameras, layout)
        ctx.dtypes = (means.dtype, quats.dtype, scales.dtype, viewmats.dtype)
        ctx.device = means.device
        radii = torch.from_numpy(radii).to(means.device)
        ctx.mark_non_differentiable(radii)
        like = {"dtype": means.dtype, "device": means.device}
        return (
            torch.from_numpy(means2d).to(**like),
            torch.from_numpy(conics).to(**like),
            torch.from_numpy(depths).to(**like),
            radii,
        )

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, grad_depths, _grad_radii):
        inputs, (viewmats, Ks), layout = ctx.state
        n = inputs[0].shape[0]
        upstream = [
            np.zeros(shape, np.float32) if g is None else float32_array(g)
            for g, shape in ((grad_means2d, (n, 2)), (grad_conics, (n, 3)), (grad_depths, (n,)))
        ]
        camera = ctx.needs_input_grad[4]
        per_view = [
            cpu_projection.project_backward(*(a[span] for a in inputs), viewmats[v], Ks[v], *layout.sizes[v],
                                            layout.blurs[v], *(g[span] for g in upstream), camera)
            for v, span in enumerate(layout.spans)
        ]
        *gaussian_parts, viewmat_parts = zip(*per_view, strict=True)
        grads = [np.concatenate(parts) for parts in gaussian_parts]
        grads.append(np.stack(viewmat_parts) if camera else None)
        means, quats, scales, grad_viewmats = (
            None if g is None else torch.from_numpy(g).to(dtype=dtype, device=ctx.device)
            for g, dtype in zip(grads, ctx.dtypes, strict=True)
        )
        return means, quats, scales, None, grad_viewmats, None, None


@dataclass
class _ViewComposite:
    """One view's compositing state between forward and backward."""

    order: np.ndarray
    bins: tuple  # tile offsets, ids, pair start, pair of
    ellipses: tuple  # limits, extents
    final_t: np.ndarray
    n_contrib: np.ndarray


class _Composite(torch.autograd.Function):
    """Screen-space Gaussians of every view -> each view's (colour, accumulated depth, alpha) images,
    returned as all colours, then all depths, then all alphas."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, radii, layout):
        arrays = [float32_array(t) for t in (means2d, conics, opacities, colors, depths)]
        bg = float32_array(background)
        radii_np = np.ascontiguousarray(radii.to("cpu", torch.int32).numpy())
        n_threads = numba.get_num_threads()
        views, images = [], []
        for span, (width, height) in zip(layout.spans, layout.sizes, strict=True):
            m2d, con, opa, col, dep = (a[span] for a in arrays)
            order = _depth_order(dep, np.flatnonzero(radii_np[span] > 0))
            tile_offsets, ids, pair_start, pair_of, limits, extents = kernels.bin_tiles(
                order, m2d, con, opa, radii_np[span], width, height, n_threads
            )
            color, accum_depth, final_t, n_contrib = kernels.render_forward(
                tile_offsets, ids, m2d, con, opa, col, dep, limits, extents, bg, width, height, n_threads
            )
            views.append(_ViewComposite(order, (tile_offsets, ids, pair_start, pair_of), (limits, extents),
                                        final_t, n_contrib))
            images.append((color, accum_depth, 1.0 - final_t))
        ctx.state = (arrays, bg, views, layout)
        ctx.dtypes = (means2d.dtype, background.dtype)
        ctx.device = means2d.device
        like = {"dtype": means2d.dtype, "device": means2d.device}
        return tuple(torch.from_numpy(image).to(**like) for kind in zip(*images, strict=True) for image in kind)

    @staticmethod
    def backward(ctx, *grads):
        arrays, bg, views, layout = ctx.state
        count = len(views)
        grad_colors, grad_depths, grad_alphas = grads[:count], grads[count:2 * count], grads[2 * count:]
        n_threads = numba.get_num_threads()
        gaussian_grads, bg_grad = [], np.zeros(3, np.float64)
        for v, (view, span, (width, height)) in enumerate(zip(views, layout.spans, layout.sizes, strict=True)):
            m2d, con, opa, col, dep = (a[span] for a in arrays)
            tile_offsets, ids, pair_start, pair_of = view.bins
            upstream = [
                np.zeros(shape, np.float32) if g is None else float32_array(g)
                for g, shape in ((grad_colors[v], (height, width, 3)), (grad_depths[v], (height, width)),
                                 (grad_alphas[v], (height, width)))
            ]
            pair_grads, bg_grads = kernels.render_backward(
                tile_offsets, ids, m2d, con, opa, col, dep, *view.ellipses, bg, view.final_t, view.n_contrib,
                *upstream, width, height, n_threads,
            )
            gaussian_grads.append(kernels.reduce_pairs(view.order, pair_start, pair_of, pair_grads, m2d.shape[0]))
            bg_grad += bg_grads.sum(axis=0, dtype=np.float64)
        dtype, bg_dtype = ctx.dtypes
        grads = torch.from_numpy(np.concatenate(gaussian_grads)).to(dtype=dtype, device=ctx.device)
        grad_bg = torch.from_numpy(bg_grad).to(dtype=bg_dtype, device=ctx.device)
        return grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:9], grads[:, 9], grad_bg, None, None


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
    if any(camera.K.requires_grad for camera in cameras):
        raise NotImplementedError("the cpu backend has no gradient for K; use backend='torch'")
    means, quats, scales, opacities, colors = (
        torch.cat(tensors) if len(scenes) > 1 else tensors[0]
        for tensors in zip(*(parameters(scene) for scene in scenes), strict=True)
    )
    layout = Layout(tuple(int(scene.means.shape[0]) for scene in scenes),
                    tuple((int(camera.width), int(camera.height)) for camera in cameras),
                    tuple(float(camera.blur) for camera in cameras))
    viewmats = torch.stack([camera.viewmat for camera in cameras])
    Ks = torch.stack([camera.K for camera in cameras])
    proj = Projection(*_Project.apply(means, quats, scales, opacities, viewmats, Ks, layout))
    # Each view's means2d a piece of the projection that compositing reads, so its retained .grad is
    # that view's screen-space gradient and it stays differentiable, as the reference's is.
    count = len(scenes)
    means2d = list(proj.means2d.split(layout.counts)) if count > 1 else [proj.means2d]
    if proj.means2d.requires_grad:
        for piece in means2d:
            piece.retain_grad()
    bg = torch.zeros(3, dtype=means.dtype, device=means.device) if background is None else background.to(means)
    images = _Composite.apply(torch.cat(means2d) if count > 1 else means2d[0], proj.conics, opacities, colors,
                              proj.depths, bg, proj.radii, layout)
    outputs = []
    for v, span in enumerate(layout.spans):
        view = Projection(means2d[v], proj.conics[span], proj.depths[span], proj.radii[span])
        outputs.append(finish_output(images[v], images[count + v], images[2 * count + v], view))
    return outputs
