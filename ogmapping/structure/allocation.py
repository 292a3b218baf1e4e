"""Map densification: which coarse anchors a frame adds (``octree.allocation``, paper table "map
densification").

- ``octree`` (the paper's method): the frame's observed coarse cells are looked up in the sorted
  level-0 codes by binary search and merged in, O(frame + map) with no sort of the map, and without
  the host reading anything (``SparseVoxelOctree.insert_unread``): how many cells are new is read
  once, with the frame's keyframe test (``NewCells.settle``).
- ``unique`` ("Naive Unique"): the same anchors, found by one ``torch.unique`` over the map's
  existing coarse codes concatenated with the frame's (new = seen once, and from the frame), so
  every frame sorts the whole map.
- ``projection`` (SplaTAM's densification): the map is rendered from the frame's pose and only
  pixels it does not explain get anchors: rendered alpha below 0.5, or rendered depth behind the
  measurement by more than 50x the median depth error. Their cells are de-duplicated within the
  frame but not against the map, so cells that already hold an anchor (object edges, depth noise)
  get another one. The cells still go into the octree, so refinement sees them.

``depth`` is the frame's depth on the colour grid with the pixels allocation skips already zeroed
(``sampled_depth``); ``render`` renders the current map from the frame's pose, and only
``projection`` calls it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ogmapping.config import OctreeConfig
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.geometry import backproject, grid_points
from ogmapping.render.output import RenderOutput
from ogmapping.runtime.host_read import read
from ogmapping.structure.octree import PAD, SparseVoxelOctree

SILHOUETTE_THRESHOLD = 0.5  # SplaTAM's sil_thres
DEPTH_ERROR_FACTOR = 50.0  # SplaTAM: depth error above 50x its median marks a pixel as unexplained


def allocation_stride(settings: OctreeConfig, intrinsics: Intrinsics) -> int:
    """Pixel stride for allocation: ``octree.allocation_stride``, or with 0 the widest stride whose
    samples lie at most a quarter voxel apart at ``depth_max``, so every observed coarse cell gets a
    point at any resolution (a sparser sampling misses cells, and keyframes then depend on it)."""
    if settings.allocation_stride:
        return settings.allocation_stride
    focal = min(intrinsics.fx, intrinsics.fy)
    return max(1, int(0.25 * settings.voxel_size * focal / settings.depth_max))


def sampled_depth(settings: OctreeConfig, depth: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
    """Depth with only every ``allocation_stride``-th pixel per axis kept (others marked invalid)."""
    stride = allocation_stride(settings, intrinsics)
    if stride == 1:
        return depth
    kept = torch.zeros_like(depth)
    kept[stride // 2 :: stride, stride // 2 :: stride] = depth[stride // 2 :: stride, stride // 2 :: stride]
    return kept


@dataclass
class NewCells:
    """The codes that get a new coarse anchor: ``padded`` holds them sorted (then ``PAD``s), ``count`` says
    how many (a 0-dim tensor: with ``octree`` allocation, on the device until the host reads it)."""

    padded: torch.Tensor
    count: torch.Tensor

    def settle(self, octree: SparseVoxelOctree, count: int | None = None) -> torch.Tensor:
        """The new codes, exactly, once ``count`` is read (here, unless the caller read it with other values);
        the octree's level 0 loses its padding."""
        count = int(read(self.count)[0]) if count is None else count
        octree.trim(0, count)
        return self.padded[:count]


def allocate(strategy: str, octree: SparseVoxelOctree, depth: torch.Tensor, intrinsics: Intrinsics,
             c2w: torch.Tensor, render: Callable[[], RenderOutput] | None = None, stride: int = 1,
             unread: bool = False) -> NewCells:
    """Occupy the coarse cells ``strategy`` picks for this frame (``depth`` holds valid values only on the
    ``stride`` grid, ``sampled_depth``); returns the codes that get a new coarse anchor (unique). ``unread``
    (the static-shape step's, as on a GPU): ``octree`` allocation at fixed sizes, leaving the count on the
    device; otherwise it selects the frame's valid points and cells at once, less work where a read of the
    device costs nothing (the CPU). The same cells either way."""
    if strategy == "octree" and unread:
        return octree_allocation(octree, *grid_points(depth, intrinsics, c2w, stride))
    if strategy == "octree":
        new = octree.allocate(backproject(depth, intrinsics, c2w))
    elif strategy == "unique":
        new = unique_allocation(octree, backproject(depth, intrinsics, c2w))
    elif strategy == "projection":
        if render is None:
            raise ValueError("projection allocation needs a render of the current map")
        new = projection_allocation(octree, depth, intrinsics, c2w, render)
    else:
        raise ValueError(f"unknown allocation strategy {strategy!r}")
    return NewCells(new, torch.tensor(new.numel()))


def octree_allocation(octree: SparseVoxelOctree, points: torch.Tensor, valid: torch.Tensor) -> NewCells:
    """Observed coarse cells not in the octree yet (a sort of the frame's codes, binary search and a linear
    merge), from the frame's ``points`` where ``valid``; the octree is left padded until ``NewCells.settle``."""
    codes = torch.where(valid, octree.codes_of(torch.where(valid.unsqueeze(-1), points, 0.0), 0, checked=False), PAD)
    return NewCells(*octree.insert_unread(codes, 0))


def unique_allocation(octree: SparseVoxelOctree, points: torch.Tensor) -> torch.Tensor:
    """The same cells as ``octree_allocation``, by a unique over all map codes plus the frame's."""
    existing = octree.keys(0)
    observed = octree.observed(points)
    union, inverse, counts = torch.unique(torch.cat([existing, observed]), return_inverse=True, return_counts=True)
    new = observed[counts[inverse[existing.numel():]] == 1]
    octree.assign(union, 0)  # the union is the level's new sorted code set
    return new


def unexplained_pixels(depth: torch.Tensor, output: RenderOutput) -> torch.Tensor:
    """SplaTAM's non-presence mask: silhouette < 0.5, or rendered depth behind the measured one by
    more than 50x the median depth error (median over the whole image, unmeasured pixels as 0)."""
    error = (depth - output.depth).abs() * (depth > 0)
    behind = (output.depth > depth) & (error > DEPTH_ERROR_FACTOR * error.median())
    return ((output.alpha < SILHOUETTE_THRESHOLD) | behind) & (depth > 0)


def projection_allocation(octree: SparseVoxelOctree, depth: torch.Tensor, intrinsics: Intrinsics,
                          c2w: torch.Tensor, render: Callable[[], RenderOutput]) -> torch.Tensor:
    """Coarse cells of the pixels the current map does not explain, new or not."""
    if octree.count(0) == 0:
        selected = depth  # an empty map explains nothing
    else:
        with torch.no_grad():
            output = render()
        selected = torch.where(unexplained_pixels(depth, output), depth, torch.zeros_like(depth))
    codes = octree.observed(backproject(selected, intrinsics, c2w))
    octree.insert(codes, 0)
    return codes
