"""Reference rasterizer: pure torch and autograd, the definition the other backends must match.

Per pixel, Gaussians go front to back: ``alpha = min(ALPHA_MAX, opacity * exp(-power))``; a
Gaussian with ``alpha < ALPHA_MIN`` is skipped; compositing stops before the first Gaussian that
would take the transmittance below TRANSMITTANCE_MIN. Pixels are processed one 16x16 tile at a
time (only Gaussians whose bounding square touches the tile and that reach one of its pixels),
each tile under activation checkpointing, so memory stays bounded by one tile's work even for
large scenes.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from ogmapping.render.output import RenderOutput, finish_output
from ogmapping.render.projection import project_gaussians, tile_grid
from ogmapping.render.rules import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN
from ogmapping.render.tiles import TILE_SIZE, tile_lists
from ogmapping.render.views import Camera, Splats, check_batch, parameters


def tile_alphas(
    pixels: torch.Tensor, means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor
) -> torch.Tensor:
    """Alpha (P, G) of Gaussians at pixel centres (P, 2), zero where below ALPHA_MIN."""
    dx = pixels[:, :1] - means2d[:, 0]
    dy = pixels[:, 1:] - means2d[:, 1]
    a, b, c = conics.unbind(-1)
    power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(opacities * torch.exp(-power), max=ALPHA_MAX)
    return torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))


def composite_tile(
    pixels: torch.Tensor,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite depth-sorted Gaussians over pixel centres (P, 2).

    Returns the weighted colour sum (P, 3), weighted depth sum (P,) and final transmittance (P,).
    """
    alpha = tile_alphas(pixels, means2d, conics, opacities)
    with torch.no_grad():
        included = torch.cumprod(1.0 - alpha, dim=1) >= TRANSMITTANCE_MIN
    alpha = torch.where(included, alpha, torch.zeros_like(alpha))
    transmittance = torch.cumprod(1.0 - alpha, dim=1)
    before = torch.cat([torch.ones_like(transmittance[:, :1]), transmittance[:, :-1]], dim=1)
    weights = alpha * before
    return weights @ colors, weights @ depths, transmittance[:, -1]


@torch.no_grad()
def active_gaussians(
    pixels: torch.Tensor, means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor
) -> torch.Tensor:
    """Which depth-sorted Gaussians (G,) matter to some pixel: composited there, or the one that
    stops compositing there. Every other one multiplies each pixel's transmittance by exactly 1
    before its stop, so dropping it changes no output and spares the differentiable pass."""
    alpha = tile_alphas(pixels, means2d, conics, opacities)
    transmittance = torch.cumprod(1.0 - alpha, dim=1)
    before = torch.cat([torch.ones_like(transmittance[:, :1]), transmittance[:, :-1]], dim=1)
    return ((alpha > 0) & (before >= TRANSMITTANCE_MIN)).any(0)


def rasterize(splats: Splats, camera: Camera, background: torch.Tensor | None = None) -> RenderOutput:
    """Render with torch ops only; see ``ogmapping.render.rasterize`` for the arguments."""
    means, quats, scales, opacities, colors = parameters(splats)
    viewmat, K, width, height, blur = camera.viewmat, camera.K, camera.width, camera.height, camera.blur
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height, blur)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    bg = torch.zeros(3, dtype=means.dtype, device=means.device) if background is None else background.to(means)
    n_x, n_y = tile_grid(width, height, TILE_SIZE)
    offsets, ids = tile_lists(proj.means2d, proj.depths, proj.radii, width, height, TILE_SIZE)
    offsets = offsets.tolist()

    # Sums over empty slices: zeros that keep the outputs in the autograd graph even when no
    # Gaussian reaches a pixel, so ``loss.backward()`` works on empty or fully culled views.
    anchor = sum(t[:0].sum() for t in (proj.means2d, proj.conics, proj.depths, opacities, colors))
    color = bg.expand(height, width, 3) + anchor
    accum_depth = means.new_zeros(height, width) + anchor
    transmittance_final = means.new_ones(height, width) + anchor
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (proj.means2d, proj.conics, opacities, colors, proj.depths, bg)
    )
    for tile_index in range(n_x * n_y):
        start, end = offsets[tile_index], offsets[tile_index + 1]
        if start == end:
            continue
        ty, tx = divmod(tile_index, n_x)
        x0, y0 = tx * TILE_SIZE, ty * TILE_SIZE
        x1, y1 = min(x0 + TILE_SIZE, width), min(y0 + TILE_SIZE, height)
        rows = torch.arange(y0, y1, dtype=means.dtype, device=means.device) + 0.5
        cols = torch.arange(x0, x1, dtype=means.dtype, device=means.device) + 0.5
        grid_y, grid_x = torch.meshgrid(rows, cols, indexing="ij")
        pixels = torch.stack([grid_x.reshape(-1), grid_y.reshape(-1)], dim=-1)
        sel = ids[start:end]
        sel = sel[active_gaussians(pixels, proj.means2d[sel], proj.conics[sel], opacities[sel])]
        if sel.numel() == 0:
            continue
        args = (pixels, proj.means2d[sel], proj.conics[sel], opacities[sel], colors[sel], proj.depths[sel])
        if needs_grad:
            c_sum, d_sum, t_final = checkpoint(composite_tile, *args, use_reentrant=False)
        else:
            c_sum, d_sum, t_final = composite_tile(*args)
        shape = (y1 - y0, x1 - x0)
        color[y0:y1, x0:x1] = (c_sum + t_final.unsqueeze(-1) * bg).reshape(*shape, 3)
        accum_depth[y0:y1, x0:x1] = d_sum.reshape(shape)
        transmittance_final[y0:y1, x0:x1] = t_final.reshape(shape)
    return finish_output(color, accum_depth, 1.0 - transmittance_final, proj.means2d, proj.radii)



def rasterize_batch(scenes: list[Splats], cameras: list[Camera],
                    background: torch.Tensor | None = None) -> list[RenderOutput]:
    """Scene i into camera i, one ``rasterize`` after another: the definition of a batched render."""
    check_batch(scenes, cameras)
    return [
        rasterize(scene, camera, background) for scene, camera in zip(scenes, cameras, strict=True)
    ]
