"""Compiled CPU rasterizer: Numba projection and compositing, each with a hand-written backward.

Two ``autograd.Function``s chained by autograd: projection (``cpu_projection``) turns the Gaussian
parameters into screen-space means, conics, depths and radii, and compositing (``cpu_kernels``)
turns those into images. Keeping ``means2d`` a separate autograd node is what gives it the
``.grad`` refinement reads. Both run float32 kernels; results follow exactly the rules of the
torch reference and come back in the input dtype.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from ogmapping.arrays import float32_array
from ogmapping.render import cpu_kernels as kernels
from ogmapping.render import cpu_projection
from ogmapping.render.output import RenderOutput, finish_output
from ogmapping.render.projection import Projection


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


class _Project(torch.autograd.Function):
    """Gaussian parameters -> (means2d, conics, depths, radii); opacity only culls, so gets no gradient."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height):
        inputs = [float32_array(t) for t in (means, quats, scales, opacities, viewmat, K)]
        means2d, conics, depths, radii = cpu_projection.project_forward(*inputs, width, height)
        ctx.state = (inputs, width, height)
        ctx.dtypes = (means.dtype, quats.dtype, scales.dtype)
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
        inputs, width, height = ctx.state
        n = inputs[0].shape[0]
        upstream = [
            np.zeros(shape, np.float32) if g is None else float32_array(g)
            for g, shape in ((grad_means2d, (n, 2)), (grad_conics, (n, 3)), (grad_depths, (n,)))
        ]
        grads = cpu_projection.project_backward(*inputs, width, height, *upstream)
        means, quats, scales = (
            torch.from_numpy(g).to(dtype=dtype, device=ctx.device) for g, dtype in zip(grads, ctx.dtypes, strict=True)
        )
        return means, quats, scales, None, None, None, None, None


class _Composite(torch.autograd.Function):
    """Screen-space Gaussians -> (colour, accumulated depth, alpha) images."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, radii, width, height):
        arrays = [float32_array(t) for t in (means2d, conics, opacities, colors, depths, background)]
        m2d, con, opa, col, dep, bg = arrays
        radii_np = np.ascontiguousarray(radii.to("cpu", torch.int32).numpy())
        order = _depth_order(dep, np.flatnonzero(radii_np > 0))
        n_threads = numba.get_num_threads()
        tile_offsets, ids, pair_start, pair_of, limits, extents = kernels.bin_tiles(
            order, m2d, con, opa, radii_np, width, height, n_threads
        )
        ellipses = (limits, extents)
        color, accum_depth, final_t, n_contrib = kernels.render_forward(
            tile_offsets, ids, m2d, con, opa, col, dep, *ellipses, bg, width, height, n_threads
        )
        ctx.state = (order, tile_offsets, ids, pair_start, pair_of, arrays, ellipses, final_t, n_contrib, width, height)
        ctx.dtypes = (means2d.dtype, background.dtype)
        ctx.device = means2d.device
        like = {"dtype": means2d.dtype, "device": means2d.device}
        return (
            torch.from_numpy(color).to(**like),
            torch.from_numpy(accum_depth).to(**like),
            torch.from_numpy(1.0 - final_t).to(**like),
        )

    @staticmethod
    def backward(ctx, grad_color, grad_depth, grad_alpha):
        order, tile_offsets, ids, pair_start, pair_of, arrays, ellipses, final_t, n_contrib, width, height = ctx.state
        m2d, con, opa, col, dep, bg = arrays
        pair_grads, bg_grads = kernels.render_backward(
            tile_offsets, ids, m2d, con, opa, col, dep, *ellipses, bg, final_t, n_contrib,
            float32_array(grad_color), float32_array(grad_depth), float32_array(grad_alpha), width, height,
            numba.get_num_threads(),
        )
        grads = torch.from_numpy(kernels.reduce_pairs(order, pair_start, pair_of, pair_grads, m2d.shape[0]))
        dtype, bg_dtype = ctx.dtypes
        grads = grads.to(dtype=dtype, device=ctx.device)
        grad_bg = torch.from_numpy(bg_grads.sum(axis=0, dtype=np.float64)).to(dtype=bg_dtype, device=ctx.device)
        return grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:9], grads[:, 9], grad_bg, None, None, None


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
    """Render with the compiled kernels; see ``ogmapping.render.rasterize`` for the arguments.

    Camera poses and intrinsics are fixed here: the projection's backward has no gradient for them,
    so asking for one is an error rather than a silent zero.
    """
    if viewmat.requires_grad or K.requires_grad:
        raise NotImplementedError("the cpu backend has no gradient for viewmat or K; use backend='torch'")
    proj = Projection(*_Project.apply(means, quats, scales, opacities, viewmat, K, int(width), int(height)))
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    bg = torch.zeros(3, dtype=means.dtype, device=means.device) if background is None else background.to(means)
    color, accum_depth, alpha = _Composite.apply(
        proj.means2d, proj.conics, opacities, colors, proj.depths, bg, proj.radii, int(width), int(height)
    )
    return finish_output(color, accum_depth, alpha, proj)
