"""Anchor-based progressive refinement and opacity pruning (paper 3.2).

Per level l: voxel size gamma_l = gamma_0 / 4**l and threshold tau_l = tau_0 * 2**l. A Gaussian of
anchor v whose mean screen-space gradient reaches tau_{l_v} proposes an anchor of level l_v at its
position; if that cell already holds an anchor of level l_v the proposal is promoted to level
l_v + 1. A Gaussian that has spawned an anchor never spawns again. Proposals past the finest level,
or into a cell that already exists at the promoted level, are dropped.

``refine.growth`` picks the growth rule (paper table "progressive map refinement"): ``anchor`` is
the rule above (``propose``), ``error`` Scaffold-GS's error-based growth (``propose_error``), and
``none`` grows nothing (pruning still runs).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ogmapping.config import Growth, RefineConfig
from ogmapping.model.gaussians import GaussianSet
from ogmapping.model.static_gaussians import DrawnGaussianSet
from ogmapping.structure.anchors import AnchorMap, cell_size
from ogmapping.structure.octree import SparseVoxelOctree


def accumulate(anchors: AnchorMap, gaussians: GaussianSet, means2d_grad: torch.Tensor | None,
               visible: torch.Tensor, width: int, height: int) -> None:
    """Add one render's screen-space gradient norms and opacities to the anchors' statistics.

    Pixel gradients are scaled by half the image size (NDC units, as 3DGS does), so thresholds do
    not depend on resolution.
    """
    anchors.observations[gaussians.anchor_rows] += 1
    anchors.max_opacity[gaussians.anchor_rows] = torch.maximum(
        anchors.max_opacity[gaussians.anchor_rows], gaussians.anchor_opacity
    )
    if means2d_grad is None or len(gaussians) == 0:
        return
    # Scaled by Python numbers, not a new tensor (a host-to-device copy per render on CUDA); every
    # Gaussian, adding 0 where it is not visible, instead of a gather of the visible ones (its
    # data-dependent size makes the host wait for the device). Each (row, slot) appears once per
    # render, so the sums are the same to the bit.
    norms = _gradient_norms(means2d_grad, visible, width, height)
    rows, slots = gaussians.rows, gaussians.slots
    anchors.grad_sum.index_put_((rows, slots), norms.to(anchors.grad_sum), accumulate=True)
    anchors.grad_count.index_put_((rows, slots), visible.to(rows.dtype), accumulate=True)


def accumulate_drawn(anchors: AnchorMap, gaussians: DrawnGaussianSet, means2d_grad: torch.Tensor | None,
                     visible: torch.Tensor, width: int, height: int) -> None:
    """``accumulate`` for a view decoded with static shapes (``static_gaussians``): Gaussian i is slot
    i % n of buffer row i // n, so the sums go straight into the buffers, counting the drawn Gaussians only."""
    observations, max_opacity = anchors.buffer("observations"), anchors.buffer("max_opacity")
    observations += gaussians.in_view
    torch.maximum(max_opacity, torch.where(gaussians.in_view, gaussians.anchor_opacity, -torch.inf), out=max_opacity)
    if means2d_grad is None:
        return
    counted = visible & gaussians.drawn
    anchors.buffer("grad_sum").view(-1).add_(_gradient_norms(means2d_grad, counted, width, height))
    anchors.buffer("grad_count").view(-1).add_(counted)


def _gradient_norms(means2d_grad: torch.Tensor, counted: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Each Gaussian's screen-space gradient norm in NDC units where ``counted``, else 0."""
    scaled = torch.stack([means2d_grad[:, 0] * (width / 2.0), means2d_grad[:, 1] * (height / 2.0)], dim=-1)
    return torch.where(counted, scaled.norm(dim=-1), 0.0)


@dataclass
class Proposals:
    codes: torch.Tensor
    levels: torch.Tensor
    parents: torch.Tensor  # anchor row each new anchor grew from


def _mean_gradient(anchors: AnchorMap) -> torch.Tensor:
    """Each Gaussian's mean screen-space gradient over the interval, (anchors, n_offsets)."""
    return anchors.grad_sum / anchors.grad_count.clamp_min(1)


def _strongest(candidate: torch.Tensor, mean_grad: torch.Tensor, limit: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows, slots) of the candidate Gaussians, at most ``limit`` of them (the largest gradients)."""
    rows, slots = torch.nonzero(candidate, as_tuple=True)
    if rows.numel() > limit:
        strongest = torch.topk(mean_grad[rows, slots], limit).indices
        rows, slots = rows[strongest], slots[strongest]
    return rows, slots


def _gaussian_positions(anchors: AnchorMap, rows: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """World positions p_v + s_v * o_v^i of the given Gaussians."""
    return (anchors.positions[rows] + anchors.offsets.detach()[rows, slots]
            * torch.exp(anchors.log_scales.detach()[rows])).to(torch.float32)


def _candidates(anchors: AnchorMap, octree: SparseVoxelOctree, candidate: torch.Tensor, mean_grad: torch.Tensor,
                limit: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(rows, slots, positions) of the strongest candidates whose positions the octree can code: a
    Gaussian that optimisation carried beyond the map's range grows nothing rather than failing the frame."""
    rows, slots = _strongest(candidate, mean_grad, limit)
    positions = _gaussian_positions(anchors, rows, slots)
    inside = octree.holds(positions)
    return rows[inside], slots[inside], positions[inside]


def propose(anchors: AnchorMap, octree: SparseVoxelOctree, config: RefineConfig) -> Proposals:
    """Anchor-based growth (the paper's): new anchors from Gaussians over their own level's
    threshold, promoted one level where the cell is taken; marks those Gaussians as spawned."""
    mean_grad = _mean_gradient(anchors)
    thresholds = config.grad_threshold * torch.pow(2.0, anchors.levels.to(mean_grad)).unsqueeze(1)
    candidate = (mean_grad >= thresholds) & (anchors.grad_count >= config.min_observations) & ~anchors.spawned
    rows, slots, positions = _candidates(anchors, octree, candidate, mean_grad, config.max_new_anchors)
    levels = anchors.levels[rows].clone()
    codes = torch.zeros_like(levels)
    keep = torch.zeros_like(levels, dtype=torch.bool)
    for level in range(octree.max_level + 1):
        at_level = levels == level
        if not bool(at_level.any()):
            continue
        own = octree.codes_of(positions[at_level], level)
        occupied = octree.contains(own, level)
        promoted_level = level + 1
        if promoted_level <= octree.max_level:
            finer = octree.codes_of(positions[at_level], promoted_level)
            promoted_free = ~octree.contains(finer, promoted_level)
        else:
            finer = own
            promoted_free = torch.zeros_like(occupied)
        new_level = torch.where(occupied, torch.full_like(own, promoted_level), torch.full_like(own, level))
        codes[at_level] = torch.where(occupied, finer, own)
        keep[at_level] = ~occupied | promoted_free
        levels[at_level] = new_level
    anchors.spawned[rows[keep], slots[keep]] = True
    codes, levels, parents = codes[keep], levels[keep], rows[keep]
    first = torch.cat([_first_occurrence(codes, levels == level) for level in range(octree.max_level + 1)])
    return Proposals(codes=codes[first], levels=levels[first], parents=parents[first])


def propose_error(anchors: AnchorMap, octree: SparseVoxelOctree, config: RefineConfig) -> Proposals:
    """Scaffold-GS's error-based growth: every Gaussian whose mean gradient reaches tau_0, whatever
    its anchor's level, proposes at each level m = 0..max_level whose tau_0 * 2**m it reaches an
    anchor in its level-m cell, kept where that cell is free. No promotion, and Gaussians are not
    marked: one may spawn again in a later interval."""
    mean_grad = _mean_gradient(anchors)
    candidate = (mean_grad >= config.grad_threshold) & (anchors.grad_count >= config.min_observations)
    rows, slots, positions = _candidates(anchors, octree, candidate, mean_grad, config.max_new_anchors)
    gradients = mean_grad[rows, slots]
    codes, levels, parents = [], [], []
    for level in range(octree.max_level + 1):
        reached = gradients >= config.grad_threshold * 2.0**level
        own = octree.codes_of(positions[reached], level)
        first = _first_occurrence(own, ~octree.contains(own, level))
        codes.append(own[first])
        levels.append(torch.full_like(own[first], level))
        parents.append(rows[reached][first])
    return Proposals(codes=torch.cat(codes), levels=torch.cat(levels), parents=torch.cat(parents))


# Every value of ``refine.growth`` and its rule; ``none`` has none.
GROWTH: dict[Growth, Callable[[AnchorMap, SparseVoxelOctree, RefineConfig], Proposals] | None] = {
    "anchor": propose, "error": propose_error, "none": None,
}


def _first_occurrence(codes: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Indices (into ``codes``) of the first occurrence of each distinct code where ``mask``."""
    indices = torch.nonzero(mask).squeeze(-1)
    if indices.numel() == 0:
        return indices
    _, inverse = torch.unique(codes[indices], return_inverse=True)
    first = torch.full((int(inverse.max()) + 1,), indices.numel(), dtype=torch.int64, device=codes.device)
    first.scatter_reduce_(0, inverse, torch.arange(indices.numel(), device=codes.device), reduce="amin")
    return indices[first]


def grow(anchors: AnchorMap, octree: SparseVoxelOctree, config: RefineConfig, voxel_size: float,
         optimizer: torch.optim.Optimizer | None) -> int:
    """Insert the anchors ``refine.growth`` proposes into the octree and the map; returns how many
    were added (none with ``growth = "none"``)."""
    rule = GROWTH[config.growth]
    if rule is None:
        return 0
    proposals = rule(anchors, octree, config)
    total = int(proposals.codes.numel())
    if total == 0:
        return 0
    for level in range(octree.max_level + 1):
        octree.insert(proposals.codes[proposals.levels == level], level)
    positions = octree.centers_by_level(proposals.codes, proposals.levels)
    features = anchors.features.detach()[proposals.parents] if anchors.with_features else None
    colours = anchors.colours.detach()[proposals.parents] if anchors.with_colours else None
    owners = anchors.keyframe[proposals.parents].clone()  # a grown anchor belongs to its parent's keyframe
    anchors.add(proposals.codes, proposals.levels, positions, cell_size(voxel_size, proposals.levels),
                features, optimizer, colours, owners)
    return total


def prune(anchors: AnchorMap, config: RefineConfig, optimizer: torch.optim.Optimizer | None) -> int:
    """Remove anchors seen often enough whose Gaussians all stayed below the opacity threshold.

    Only anchors rendered in this interval are judged (as Scaffold-GS does): an anchor outside
    every window view since the last step has no opacity on record, and is not faint for that.
    """
    rendered = anchors.max_opacity > -torch.inf
    weak = (
        rendered
        & (anchors.observations >= config.prune_min_observations)
        & (anchors.max_opacity < config.prune_opacity)
    )
    removed = int(weak.sum())
    if removed:
        anchors.keep(~weak, optimizer)
    return removed


def end_interval(anchors: AnchorMap) -> None:
    """Start a fresh accumulation window after each grow/prune step."""
    anchors.reset_statistics()
