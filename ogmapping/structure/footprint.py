"""A view's footprint: the occupied coarsest octree cells it sees, and how much two footprints overlap.

A footprint is a mask over a sorted code tensor, the octree's level-0 keys when it was taken
(``SparseVoxelOctree.seen_mask``), not the codes themselves: picking them out would make the host wait
for the device. Two footprints taken on the same keys tensor compare with masks alone; the keyframe
test reads its overlap together with the frame's new-cell count, in one wait.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Footprint:
    """The codes of ``keys`` where ``seen``."""

    keys: torch.Tensor  # sorted codes (a padded level may end in PAD, never seen)
    seen: torch.Tensor  # bool, keys' shape

    @classmethod
    def of_codes(cls, codes: torch.Tensor) -> Footprint:
        """The footprint of these sorted unique codes."""
        return cls(codes, torch.ones_like(codes, dtype=torch.bool))

    def codes(self) -> torch.Tensor:
        """The seen codes, sorted (picking them out makes the host wait for the device)."""
        return self.keys[self.seen]


def overlap(first: Footprint, second: Footprint) -> torch.Tensor:
    """N_overlap / N_union (1 for two empty footprints) as a 0-dim float64 tensor on the footprints' device:
    masks alone when both were taken on the same keys, else their codes by binary search."""
    if first.keys is second.keys:
        common = (first.seen & second.seen).sum()
        union = first.seen.sum() + second.seen.sum() - common
    else:
        a, b = first.codes(), second.codes()
        if b.numel() == 0:
            common = torch.zeros((), dtype=torch.int64, device=a.device)
        else:
            common = (b[torch.searchsorted(b, a).clamp_max(b.numel() - 1)] == a).sum()
        union = a.numel() + b.numel() - common
    ratio = common.to(torch.float64) / union.to(torch.float64).clamp_min(1)
    return torch.where(union > 0, ratio, 1.0)
