"""Anchor colours: a learnable colour logit per anchor, next to the shared colour decoder.

The decoder couples every anchor's colour through shared weights and a feature that a few online
steps per frame move slowly; with ``model.anchor_colour`` each anchor also carries a colour logit
added to the decoder's output for all n of its Gaussians, learned at its own, higher rate, and a
grown anchor takes its parent's. It starts at zero (the decoder's colour) or, with
``model.anchor_colour_start=cell``, so that its Gaussians' mean logit is that of the mean colour of
the allocating frame's depth points in its cell: the better start where colour and depth are
registered (Replica), a worse one where they are not (7-Scenes; bench/RESULTS.md). The mean, not
the pixel at the cell's centre: on 7-Scenes one pixel carries the sensor's noise.
"""

from __future__ import annotations

import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.geometry import backproject, valid_depth
from ogmapping.structure.octree import SparseVoxelOctree

COLOUR_MARGIN = 1.0 / 255.0  # keeps the logit finite for black and white pixels


def with_anchor_colours(color_logits: torch.Tensor, colours: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """The colour decoder's (V, 3n) logits plus each anchor's own colour logit on all n of its Gaussians."""
    n = color_logits.shape[1] // 3
    return color_logits + colours.index_select(0, rows).repeat(1, n)


def colour_sample_stride(voxel_size: float, depth_max: float, intrinsics: Intrinsics) -> int:
    """Pixel stride for the cells' mean colours: samples half a coarsest cell apart at ``depth_max``,
    so every cell gets several (every pixel cost 80 ms a frame at 600x340 on one thread)."""
    return max(1, int(0.5 * voxel_size * min(intrinsics.fx, intrinsics.fy) / depth_max))


def cell_colour_logits(octree: SparseVoxelOctree, codes: torch.Tensor, rgb: torch.Tensor, depth: torch.Tensor,
                       intrinsics: Intrinsics, c2w: torch.Tensor, stride: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Logits (N, 3) of the mean colour of the frame's depth points (every ``stride``-th pixel per
    axis) inside each coarsest cell of ``codes`` (sorted, non-empty), and which cells any point fell
    in (the others' logits are zero)."""
    start = stride // 2
    depth, rgb = depth[start::stride, start::stride], rgb[start::stride, start::stride]
    intrinsics = intrinsics.strided(stride, start) if stride > 1 else intrinsics
    points = backproject(depth, intrinsics, c2w)
    colours = rgb[valid_depth(depth)].to(torch.float32)
    codable = octree.holds(points)
    points, colours = points[codable], colours[codable]
    point_codes = octree.codes_of(points, 0)
    slots = torch.searchsorted(codes, point_codes).clamp_max(codes.numel() - 1)
    inside = codes[slots] == point_codes
    sums = torch.zeros(codes.numel(), 3, dtype=torch.float32, device=codes.device)
    counts = torch.zeros(codes.numel(), dtype=torch.float32, device=codes.device)
    sums.index_add_(0, slots[inside], colours[inside])
    counts.index_add_(0, slots[inside], torch.ones_like(slots[inside], dtype=torch.float32))
    seen = counts > 0
    logits = torch.zeros_like(sums)
    logits[seen] = torch.logit((sums[seen] / counts[seen].unsqueeze(1)).clamp(COLOUR_MARGIN, 1.0 - COLOUR_MARGIN))
    return logits, seen
