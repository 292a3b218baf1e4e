"""Pose corrections of keyframes already mapped: the anchors each keyframe owns follow it rigidly.

A client's SLAM corrects past poses when it closes a loop. For each corrected keyframe the rigid
delta D = corrected @ inverse(old) (old: its pose as the client gave it, or as the last correction left it) moves the
anchors that belong to it (``AnchorMap`` row ``keyframe``): their centres p -> D p, and their
offsets rotated with it so that every Gaussian mean p + s * o lands at D (p + s * o) (the offsets are
scaled per axis by s, so o -> R (s * o) / s). The decoded rotations and the hash grid's features are
functions of the map, not of the anchor, and do not follow: the corrected keyframes join the window
for a few draws (``KeyframeSet.revisit``) so that optimisation settles what the move leaves.

Moved anchors are coded again at the cells their new centres fall in, and the octree's occupied
cells are updated set-wise: a cell that no anchor holds any more is freed, a new one is occupied.
Two anchors that land in one cell both stay (rows are never merged or dropped by a correction);
the cell is occupied once. Their centres then lie anywhere in their cells, no longer at the centre:
the map keeps them as they are (snapshots store ``anchors.positions``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ogmapping.mapping.model import MapModel
from ogmapping.structure.anchors import AnchorMap
from ogmapping.structure.octree import SparseVoxelOctree


def jump(old: np.ndarray, corrected: np.ndarray) -> tuple[float, float]:
    """How far a correction moves the camera: (metres the centre moves, degrees it turns)."""
    rotation = corrected[:3, :3] @ old[:3, :3].T
    cosine = np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(corrected[:3, 3] - old[:3, 3])), float(np.degrees(np.arccos(cosine)))


@dataclass(frozen=True)
class Moved:
    """What one batch of corrections did to the map."""

    keyframes: int
    anchors: int


def delta(old: np.ndarray, corrected: np.ndarray) -> np.ndarray:
    """D = corrected @ inverse(old), for rigid ``old``: the world motion that carries old to corrected."""
    inverse = np.eye(4)
    inverse[:3, :3] = old[:3, :3].T
    inverse[:3, 3] = -old[:3, :3].T @ old[:3, 3]
    return corrected @ inverse


def moved_rows(anchors: AnchorMap, deltas: dict[int, np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """(rows, per-row 4x4 deltas in float64) of the live anchors that belong to a corrected keyframe."""
    owners = anchors.keyframe
    rows, transforms = [], []
    for keyframe, transform in deltas.items():
        owned = torch.nonzero(owners == keyframe).squeeze(-1)
        rows.append(owned)
        transforms.append(torch.as_tensor(transform, dtype=torch.float64, device=owners.device).expand(
            owned.numel(), 4, 4))
    if not rows:
        empty = torch.empty(0, dtype=torch.int64, device=owners.device)
        return empty, torch.empty(0, 4, 4, dtype=torch.float64, device=owners.device)
    return torch.cat(rows), torch.cat(transforms)


def new_positions(model: MapModel, rows: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """The moved anchors' centres; ValueError when one leaves the range the octree can code."""
    positions = model.anchors.positions[rows].to(torch.float64)
    moved = (transforms[:, :3, :3] @ positions.unsqueeze(-1)).squeeze(-1) + transforms[:, :3, 3]
    if not bool(model.octree.holds(moved).all()):
        raise ValueError("the correction moves anchors beyond the range the map's octree can code")
    return moved


def move(model: MapModel, deltas: dict[int, np.ndarray]) -> int:
    """Move every anchor of each keyframe in ``deltas`` (position -> 4x4 delta) rigidly, written in place
    into the row buffers (hold the mapper's lock); the number of anchors moved. Nothing changes when
    ValueError is raised."""
    anchors, octree = model.anchors, model.octree
    rows, transforms = moved_rows(anchors, deltas)
    if rows.numel() == 0:
        return 0
    positions = new_positions(model, rows, transforms)
    rotations = transforms[:, :3, :3].unsqueeze(1)  # (R, 1, 3, 3) over the offsets
    levels = anchors.levels[rows]
    old_codes = anchors.codes[rows].clone()
    codes = torch.empty_like(old_codes)
    for level in range(octree.levels):
        at_level = levels == level
        codes[at_level] = octree.codes_of(positions[at_level], level)
    with torch.no_grad():
        anchors.buffer("positions")[rows] = positions.to(torch.float32)
        anchors.buffer("codes")[rows] = codes
        pairs = [(anchors.parameter("offsets"), anchors.parameter("log_scales"))]
        if model.average.enabled:
            pairs.append((anchors.average_rows["offsets"], anchors.average_rows["log_scales"]))
        for offsets, log_scales in pairs:
            scales = torch.exp(log_scales[rows].to(torch.float64)).unsqueeze(1)  # (R, 1, 3)
            world = offsets[rows].to(torch.float64) * scales
            turned = (rotations @ world.unsqueeze(-1)).squeeze(-1)
            offsets[rows] = (turned / scales).to(offsets.dtype)
    _recode_octree(anchors, octree, levels, old_codes, codes)
    return int(rows.numel())


def _recode_octree(anchors: AnchorMap, octree: SparseVoxelOctree, levels: torch.Tensor, old_codes: torch.Tensor,
                   codes: torch.Tensor) -> None:
    """Free the cells moved anchors left that no anchor holds now; occupy the cells they moved into."""
    for level in range(octree.levels):
        at_level = levels == level
        if not bool(at_level.any()):
            continue
        held = anchors.codes[anchors.levels == level]
        left = old_codes[at_level]
        octree.remove(left[~torch.isin(left, held)], level)
        octree.insert(codes[at_level], level)
