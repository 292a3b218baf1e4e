"""Tile binning in torch: which Gaussians may touch each 16x16 pixel tile, front to back.

A Gaussian is listed in every tile whose pixel area overlaps its bounding square
``[u - r, u + r] x [v - r, v + r]``; using the tile's area (not its pixel centres) leaves half a
pixel of slack, so rounding can never drop a pixel the per-pixel alpha rule would include.
"""

from __future__ import annotations

import torch

from ogmapping.render.projection import tile_grid

TILE_SIZE = 16


def tile_rects(
    means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int, tile: int = TILE_SIZE
) -> torch.Tensor:
    """Inclusive tile ranges (N, 4) as (x0, y0, x1, y1), clipped to the grid; empty where x1 < x0."""
    n_x, n_y = tile_grid(width, height, tile)
    centre = means2d.detach().double()
    r = radii.double().unsqueeze(-1)
    low = torch.floor((centre - r) / tile)
    high = torch.floor((centre + r) / tile)
    limits = torch.tensor([n_x - 1, n_y - 1], dtype=torch.float64, device=means2d.device)
    low = torch.maximum(low, torch.zeros_like(low))
    high = torch.minimum(high, limits)
    rects = torch.cat([low, high], dim=-1).long()
    empty = (radii <= 0) | (rects[:, 2] < rects[:, 0]) | (rects[:, 3] < rects[:, 1])
    rects[empty] = torch.tensor([0, 0, -1, -1], device=means2d.device)
    return rects


def tile_lists(
    means2d: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    tile: int = TILE_SIZE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-tile Gaussian lists in CSR form: ``ids[offsets[t]:offsets[t + 1]]`` sorted by depth.

    Ties in depth keep index order, the same order the cpu backend uses.
    """
    n_x, n_y = tile_grid(width, height, tile)
    device = means2d.device
    by_depth = torch.sort(depths.detach(), stable=True).indices
    rects = tile_rects(means2d, radii, width, height, tile)[by_depth]
    spans_x = (rects[:, 2] - rects[:, 0] + 1).clamp_min(0)
    counts = spans_x * (rects[:, 3] - rects[:, 1] + 1).clamp_min(0)
    owner = torch.repeat_interleave(torch.arange(by_depth.numel(), device=device), counts)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(owner.numel(), device=device) - starts[owner]
    span = spans_x[owner].clamp_min(1)
    tile_x = rects[owner, 0] + local % span
    tile_y = rects[owner, 1] + local // span
    tile_ids = tile_y * n_x + tile_x
    order = torch.sort(tile_ids, stable=True).indices
    ids = by_depth[owner[order]]
    per_tile = torch.bincount(tile_ids, minlength=n_x * n_y)
    offsets = torch.zeros(n_x * n_y + 1, dtype=torch.long, device=device)
    offsets[1:] = torch.cumsum(per_tile, 0)
    return offsets, ids
