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
from ogmapping.runtime.host_read import read
from ogmapping.structure.anchors import AnchorMap, cell_size
from ogmapping.structure.octree import PAD, SparseVoxelOctree


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
    norms = gradient_norms(means2d_grad, visible, width, height)
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
    anchors.buffer("grad_sum").view(-1).add_(gradient_norms(means2d_grad, counted, width, height))
    anchors.buffer("grad_count").view(-1).add_(counted)


def gradient_norms(means2d_grad: torch.Tensor, counted: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Each Gaussian's screen-space gradient norm in NDC units where ``counted``, else 0."""
    scaled = torch.stack([means2d_grad[:, 0] * (width / 2.0), means2d_grad[:, 1] * (height / 2.0)], dim=-1)
    return torch.where(counted, scaled.norm(dim=-1), 0.0)


@dataclass
class Proposals:
    """Anchors to add, sorted by level then code, each with the anchor row it grew from; ``counts[l]`` of them
    at level l. Past ``counts.sum()`` the rows are padding (``PAD`` codes) until ``settled``: ``propose``
    leaves its counts on the device, so a refinement reads them once, with its pruning count."""

    codes: torch.Tensor
    levels: torch.Tensor
    parents: torch.Tensor  # anchor row each new anchor grew from
    counts: torch.Tensor  # (levels,) int64

    def settled(self, counts: list[int]) -> Proposals:
        """The proposals without padding, given ``counts`` as read on the host."""
        total = sum(counts)
        return Proposals(self.codes[:total], self.levels[:total], self.parents[:total],
                         torch.tensor(counts, dtype=torch.int64))


def _mean_gradient(anchors: AnchorMap) -> torch.Tensor:
    """Each Gaussian's mean screen-space gradient over the interval, (anchors, n_offsets)."""
    return anchors.grad_sum / anchors.grad_count.clamp_min(1)


def _strongest(candidate: torch.Tensor, mean_grad: torch.Tensor,
               limit: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(rows, slots, valid) of the candidate Gaussians, at a fixed size: at most ``limit`` of them, all in
    row-major order if they fit, else the ``limit`` largest gradients, strongest first; ``valid`` marks the
    candidates among the rows (the rest is padding, not a selection the host would have to size)."""
    flat = candidate.reshape(-1)
    chosen = min(limit, flat.numel())
    index = torch.topk(torch.where(flat, mean_grad.reshape(-1), -torch.inf), chosen).indices
    valid = flat[index]
    position = torch.arange(chosen, device=flat.device)
    order = torch.where(valid, torch.where(flat.sum() > limit, position, index), flat.numel() + position)
    index = index[torch.sort(order).indices]
    slots = candidate.shape[1]
    return index // slots, index % slots, flat[index]


def _gaussian_positions(anchors: AnchorMap, rows: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
    """World positions p_v + s_v * o_v^i of the given Gaussians."""
    return (anchors.positions[rows] + anchors.offsets.detach()[rows, slots]
            * torch.exp(anchors.log_scales.detach()[rows])).to(torch.float32)


def propose(anchors: AnchorMap, octree: SparseVoxelOctree, config: RefineConfig) -> Proposals:
    """Anchor-based growth (the paper's): new anchors from Gaussians over their own level's threshold,
    promoted one level where the cell is taken (and again where that one is); marks those Gaussians as
    spawned. A Gaussian that optimisation carried beyond the octree's range grows nothing. Fixed sizes
    throughout, so the host waits for nothing (the counts stay on the device)."""
    last = octree.max_level
    mean_grad = _mean_gradient(anchors)
    thresholds = config.grad_threshold * torch.pow(2.0, anchors.levels.to(mean_grad)).unsqueeze(1)
    candidate = (mean_grad >= thresholds) & (anchors.grad_count >= config.min_observations) & ~anchors.spawned
    rows, slots, valid = _strongest(candidate, mean_grad, config.max_new_anchors)
    positions = _gaussian_positions(anchors, rows, slots)
    valid = valid & octree.holds(positions)
    positions = torch.where(valid.unsqueeze(-1), positions, 0.0)
    levels = torch.where(valid, anchors.levels[rows], last + 1)  # padding: a level past the last
    codes = torch.full_like(levels, PAD)
    keep = torch.zeros_like(valid)
    for level in range(last + 1):
        at_level = levels == level
        own = octree.codes_of(positions, level, checked=False)
        occupied = octree.contains(own, level)
        if level < last:
            finer = octree.codes_of(positions, level + 1, checked=False)
            promoted_free = ~octree.contains(finer, level + 1)
        else:
            finer, promoted_free = own, torch.zeros_like(occupied)
        codes = torch.where(at_level, torch.where(occupied, finer, own), codes)
        keep = torch.where(at_level, ~occupied | promoted_free, keep)
        levels = torch.where(at_level & occupied, level + 1, levels)
    spawned = anchors.spawned.view(-1)
    flat = rows * anchors.n_offsets + slots
    spawned.index_put_((flat,), spawned[flat] | keep)
    return _first_of_each(torch.where(keep, codes, PAD), torch.where(keep, levels, last + 1), rows, last + 1)


def _first_of_each(codes: torch.Tensor, levels: torch.Tensor, parents: torch.Tensor, count: int) -> Proposals:
    """Proposals of each distinct (level, code) among ``codes`` (``PAD`` and a level of ``count`` for none),
    the first in order keeping its parent, sorted by level then code, padded to the input's size."""
    order = torch.sort(codes, stable=True).indices
    order = order[torch.sort(levels[order], stable=True).indices]
    codes, levels, parents = codes[order], levels[order], parents[order]
    first = codes != PAD
    first[1:] &= (codes[1:] != codes[:-1]) | (levels[1:] != levels[:-1])
    slots = torch.where(first, torch.cumsum(first, 0) - 1, codes.numel())

    def packed(values: torch.Tensor, pad: int) -> torch.Tensor:
        out = torch.full((values.numel() + 1,), pad, dtype=values.dtype, device=values.device)
        return out.index_put_((slots,), values)[:-1]

    counts = torch.stack([(first & (levels == level)).sum() for level in range(count)])
    return Proposals(packed(codes, PAD), packed(levels, count), packed(parents, 0), counts)


def propose_error(anchors: AnchorMap, octree: SparseVoxelOctree, config: RefineConfig) -> Proposals:
    """Scaffold-GS's error-based growth: every Gaussian whose mean gradient reaches tau_0, whatever
    its anchor's level, proposes at each level m = 0..max_level whose tau_0 * 2**m it reaches an
    anchor in its level-m cell, kept where that cell is free. No promotion, and Gaussians are not
    marked: one may spawn again in a later interval. (A comparison rule: it selects on the host.)"""
    mean_grad = _mean_gradient(anchors)
    candidate = (mean_grad >= config.grad_threshold) & (anchors.grad_count >= config.min_observations)
    rows, slots, valid = _strongest(candidate, mean_grad, config.max_new_anchors)
    positions = _gaussian_positions(anchors, rows, slots)
    chosen = valid & octree.holds(positions)
    rows, slots, positions = rows[chosen], slots[chosen], positions[chosen]
    gradients = mean_grad[rows, slots]
    codes, levels, parents = [], [], []
    for level in range(octree.max_level + 1):
        reached = gradients >= config.grad_threshold * 2.0**level
        own = octree.codes_of(positions[reached], level)
        first = _first_occurrence(own, ~octree.contains(own, level))
        codes.append(own[first])
        levels.append(torch.full_like(own[first], level))
        parents.append(rows[reached][first])
    counts = torch.tensor([len(level_codes) for level_codes in codes], dtype=torch.int64)
    return Proposals(torch.cat(codes), torch.cat(levels), torch.cat(parents), counts)


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


@dataclass
class Refined:
    grown: int
    pruned: int


def refine(anchors: AnchorMap, octree: SparseVoxelOctree, config: RefineConfig, voxel_size: float,
           optimizer: torch.optim.Optimizer | None) -> Refined:
    """Grow the anchors ``refine.growth`` proposes (none with ``none``), then prune the faint ones; the host
    reads the device once, for how many anchors each level gains and how many go."""
    rule = GROWTH[config.growth]
    proposals = rule(anchors, octree, config) if rule is not None and len(anchors) else None
    weak = _faint(anchors, config)
    counts = read(proposals.counts if proposals is not None else torch.zeros(0), weak.sum())
    *per_level, pruned = (int(count) for count in counts)
    grown = _add(anchors, octree, proposals.settled(per_level), voxel_size, optimizer) if proposals is not None else 0
    if pruned:
        kept = torch.cat([~weak, torch.ones(grown, dtype=torch.bool, device=weak.device)])
        anchors.keep(kept, optimizer, len(anchors) - pruned)
    return Refined(grown, pruned)


def _add(anchors: AnchorMap, octree: SparseVoxelOctree, proposals: Proposals, voxel_size: float,
         optimizer: torch.optim.Optimizer | None) -> int:
    """Insert settled proposals into the octree (each level's already sorted, unique and free) and the map."""
    total = int(proposals.codes.numel())
    if total == 0:
        return 0
    start = 0
    for level, count in enumerate(proposals.counts.tolist()):
        if count:
            octree.insert_sorted(proposals.codes[start: start + count], level)
        start += count
    positions = octree.centers_by_level(proposals.codes, proposals.levels)
    features = anchors.features.detach()[proposals.parents] if anchors.with_features else None
    colours = anchors.colours.detach()[proposals.parents] if anchors.with_colours else None
    owners = anchors.keyframe[proposals.parents].clone()  # a grown anchor belongs to its parent's keyframe
    anchors.add(proposals.codes, proposals.levels, positions, cell_size(voxel_size, proposals.levels),
                features, optimizer, colours, owners)
    return total


def _faint(anchors: AnchorMap, config: RefineConfig) -> torch.Tensor:
    """Anchors seen often enough whose Gaussians all stayed below the opacity threshold.

    Only anchors rendered in this interval are judged (as Scaffold-GS does): an anchor outside
    every window view since the last step has no opacity on record, and is not faint for that.
    """
    rendered = anchors.max_opacity > -torch.inf
    return (
        rendered
        & (anchors.observations >= config.prune_min_observations)
        & (anchors.max_opacity < config.prune_opacity)
    )


def end_interval(anchors: AnchorMap) -> None:
    """Start a fresh accumulation window after each grow/prune step."""
    anchors.reset_statistics()
